"""Real LiDAR logs: VoxSplats built from real sweeps (`build`), a simulated sweep scored ray for ray
against the real one (`fidelity`), and the ray-drop model fitted to real no-returns (`raydrop`).
The dataset adapters that read the logs are `scube_sim.datasets`."""
