"""Parameter identification: the campaign file, identifiability, Levenberg-Marquardt, recursive
identification and pose selection.
"""
