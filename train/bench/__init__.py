"""Benchmarks: the C runtime (inference, EKF, MPC, controller step, CAN path) against Python."""
