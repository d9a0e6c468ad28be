"""Shipped training configurations (YAML), resolved by name: see `scube_sim.model.config`."""
