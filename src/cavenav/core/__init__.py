"""The vocabulary every layer shares: poses, actions and observations (`types`), the
errors and their exit statuses (`errors`), writing a file in place (`files`) and keeping
secrets out of records (`redaction`). It imports nothing else of cavenav."""
