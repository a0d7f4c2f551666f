"""The policy as C for flight controllers: export, host parity, Cortex-M4F build and QEMU bench."""
