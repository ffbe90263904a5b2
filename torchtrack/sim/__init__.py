"""Simulation: the papers' scenarios, detections drawn from ground truth, and synthetic satellite-style video."""
