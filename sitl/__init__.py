"""Software in the loop: the firmware's vehicle composed with the simulated world."""
