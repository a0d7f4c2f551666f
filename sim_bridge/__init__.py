"""The simulated world: MuJoCo digital twin, lockstep link, Gymnasium environments."""
