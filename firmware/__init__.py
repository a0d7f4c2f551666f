"""The emulated flight controller: fixed-rate loop, rate controllers, mixer, MAVLink.

Runs with numpy, onnxruntime and pymavlink; never imports mujoco, torch or a layer above
it (`fcemu.sim_bridge`, `fcemu.sitl`, the tools): tests/test_layers.py checks both.
"""
