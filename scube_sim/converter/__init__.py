"""The sensor-to-sensor converter as a product: posed camera frames to a VoxSplat.

- `profile`: `ConverterProfile`, `load_profile`, the shipped profiles (`profiles/*.yaml`) and
  `DEFAULT_PROFILE` (no torch).
- `frames`: a sample's frames from a dataset and the item a network reads from them.
- `pipeline`: `Converter` (the profile's route: the paper's networks, or measured evidence with
  the learned completion) and `convert`.
- `merge`: the completion network's cells joined with the measured scene.
- `eval/`: the converter end to end (`sensor_to_sensor`) and camera depth (`depth`).

Measured geometry lives in `scube_sim.reconstruct`, the networks in `scube_sim.model`; this room
stands above both.
"""
