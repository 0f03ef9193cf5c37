"""Bilateral teleoperation scene: a haptic master, an operator, a gripper and an egg."""
