"""
Evaluation: trajectory files, metrics and plots.

KITTI and TUM trajectory files at full precision, the KITTI odometry metric and evo-style
errors, and the plots of a run.
"""
