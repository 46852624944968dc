"""
Feature tracking: the stereo KLT tracker and its checks.

Light adaptive feature tracking (forward-backward, left-right with the disparity constraint,
bi-circular check with the adaptive threshold), bucketing of new corners, the affine refinement
of matches and the brightness maps that make KLT survive exposure changes.
"""
