"""Device drivers (current source, displacement sensor) and mock devices for smabench."""
