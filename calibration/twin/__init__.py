"""The twin on the daemon's data: column streams, campaign phases, dwell pairing, ``twin run`` in
memory, the live twin, and compensation.
"""
