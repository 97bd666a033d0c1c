"""Learning: DDM/DPM networks, training, checkpoints, FTHD, the EKF layer, denoising, tuning, export."""
