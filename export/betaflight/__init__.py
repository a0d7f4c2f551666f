"""`fcemu export --target betaflight`: Betaflight 4.6.0 with the policy's C compiled in (NEURAL mode)."""
