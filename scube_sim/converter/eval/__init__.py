"""The converter end to end, camera frames to a simulated LiDAR sweep against the exact mesh
(`sensor_to_sensor`), and the depth of camera images against rendered depth or real LiDAR (`depth`)."""
