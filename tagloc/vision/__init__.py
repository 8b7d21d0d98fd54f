"""Per-frame vision: detect, rectify, decode, identify, pose and floor odometry."""
