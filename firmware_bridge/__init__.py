"""Tracker and headset I/O for the board: transports, wire protocol, frame sync and the device simulator.

Imports `edge` for shared types only; never torch.
"""
