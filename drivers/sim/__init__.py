"""The simulated drive: a procedural road, the car and its sensors, as a drive log and live devices."""
