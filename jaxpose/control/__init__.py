"""Control: LQR, iLQR with box limits, differentiable MPC."""
