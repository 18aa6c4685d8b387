"""Grating-scale calibration: circle and target-set fits, the relation of counts to tracker points,
the whole chain, scale files and their reports.
"""
