"""Composition: the vehicle's firmware and the simulated world wired together (e.g. real Betaflight
SITL flying the twin)."""
