"""Pipeline stages, one module each in the paper's order; numpy/scipy only.

moving (1) -> cluster (2) -> associate (3) -> ground_plane (4) -> track (5)
-> hypotheses (6) -> polygon (7, the paper's refinement) -> refine (8, ours)
-> quality (9). ``vehicle`` holds the calibration vehicle's box geometry they share.
"""
