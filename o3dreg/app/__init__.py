"""Applications over the three stages: the demo, reports, pictures, bundled and synthetic data."""
