"""smabench: lab-bench application for shape-memory-alloy wire actuators."""

__version__ = "0.1.0"
