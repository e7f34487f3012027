"""The simulator as Gymnasium environments: one cave (`env`), a batch of caves
(`vector_env`), the episode's limits and the shield as wrappers (`wrappers`), and the
cave's camera and sounders served to a fake vehicle over the network (`cave_sensors`)."""
