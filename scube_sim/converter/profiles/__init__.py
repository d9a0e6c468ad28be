"""Shipped converter profiles (YAML): `converter.profile.load_profile` reads them by name."""
