"""Tracker and headset I/O for the board: every byte format (`wire`), the transports that carry them
(`transports`: serial, I2C with the BNO055 driver, CAN, SlimeVR, the headset's WebXR page), the frame
synchroniser (`sync`), the board service `edge run` runs (`service`, `config`, `commands`) and the pose
outputs (`outputs`: VMC, VRChat OSC, BVH).

The layer above the board runtime: imports `edge`, never a tool, torch or the simulator (the device
simulator is `edgetools.sim`, above it).
"""
