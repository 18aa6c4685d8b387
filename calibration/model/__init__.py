"""The robot's model: its description file, forward and inverse kinematics, base registration,
statics, gravity and stiffness, and the plausibility of joints and points.
"""
