"""Evaluation: a checkpoint's metrics on a split (`evaluate`) and the whole converter, camera
frames to a simulated LiDAR sweep against the exact mesh (`sensor_to_sensor`)."""
