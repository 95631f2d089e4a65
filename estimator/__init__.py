"""State estimation: the UKF fusing 500 Hz IMU and 100 Hz MoCap. Pure numerics, no I/O."""
