"""Every byte format the board speaks, one module per format, with its specification beside it.

    framing.py     COBS + CRC-16 frames of the serial links               protocol.md
    messages.py    TRACKER_SAMPLES, HEADSET_POSE, TARGET, POSE_FRAME;     protocol.md
                   FrameReader
    can_frames.py  a CAN tracker node's two frames and their decoder      can.md
    slimevr.py     the SlimeVR tracker protocol (UDP)                     slimevr.md
    webxr.py       the headset page's WebSocket messages (pairing, poses)  docs/headset.md
    q14.py         the one Q14 quaternion codec the binary formats share

Pure functions of bytes: no ports, sockets or buses here (those are firmware_bridge.transports).
"""
