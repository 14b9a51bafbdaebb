"""The simulated world (pybullet) and the simulated devices behind the drivers. Never imported by an agent."""
