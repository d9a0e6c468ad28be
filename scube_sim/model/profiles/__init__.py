"""Shipped converter profiles (YAML): `model.converter.load_profile` reads them by name."""
