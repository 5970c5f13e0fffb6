"""Real device backends (ur_rtde, dynamixel_sdk, OpenCV, GenICam via harvesters); used only with
--backend hw."""
