"""Real device backends (ur_rtde, dynamixel_sdk, OpenCV, GenICam via harvesters, a Gardasoft RT
lighting controller over TCP); used only with --backend hw."""
