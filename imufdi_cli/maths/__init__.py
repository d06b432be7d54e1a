"""Shared maths below the detectors: projections, noise models, sequential tests."""
