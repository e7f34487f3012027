"""What keeps the vehicle off the rock and out of loops, from what it senses alone: the
safety shield (`shield`), the position reckoned from the commanded moves (`reckoning`),
the map of the passage built from depth (`cave_map`) and what counts as headway
(`headway`). It never reads the cave model: a real vehicle has none."""
