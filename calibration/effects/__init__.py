"""The closed loop: the library of physical effects, their shapes and scores, prediction with every
modelled effect, the loop itself, ``calibrate()`` and its report.
"""

# The kinds register themselves in effect_base.KINDS when effect_kinds gathers them: imported
# here, so the registry is full whatever module of the package is imported first.
from calibration.effects import effect_kinds as effect_kinds
