"""Benchmarks: every `fcemu bench` figure but `mcu`, and the PID tuning script."""
