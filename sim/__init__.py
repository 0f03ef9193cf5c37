"""Scene-driven physics simulator of the FBG end-effector (stands in for the gripper)."""
