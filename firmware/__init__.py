"""The emulated flight controller: fixed-rate loop, rate controllers, mixer, MAVLink.

Runs with numpy, onnxruntime, pymavlink and mujoco only; never imports torch,
`training`, `export` or `evaluation`.
"""
