"""The closed loop: the library of physical effects, their shapes and scores, prediction with every
modelled effect, the loop itself, ``calibrate()`` and its report.
"""
