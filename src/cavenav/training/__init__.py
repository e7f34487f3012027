"""Learning from flights: training data for vision-language pilots (`dataset`)."""
