"""Real device backends (ur_rtde, dynamixel_sdk, OpenCV); used only with --backend hw."""
