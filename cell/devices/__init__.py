"""The devices the closed loop drives: their interfaces (`interfaces`: arm, lamp rig, camera,
lighting controller), the kinematics of the lamp rig (`rig`) and the UR5e (`ur5e`), a run's hold
on the devices (`session`), the Dynamixel control table (`servo`), the operator at the cell
(`operator`) and the real adapters (`hw`: ur_rtde, dynamixel_sdk, OpenCV, GenICam, a Gardasoft RT
lighting controller).

Layer 4: imports `cell.core`, `cell.physics`, `cell.task`; never `sim`. Only `cell.run.backends`
imports `hw`."""
