"""
Egomotion estimation from stereo correspondences.

Camera model and calibration, trifocal transfer, the motion model, the Kalman filters (ISPKF,
EKF, IEKF, UKF behind one interface), RANSAC, the estimator that combines them, and the online
refinement of the stereo rig.
"""
