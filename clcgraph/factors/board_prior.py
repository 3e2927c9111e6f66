"""Light regularization of board poses that only LIDARs saw.

A LIDAR measures only the board's plane, so a board seen by LIDARs alone has three free
directions: translation within the plane (board x, y) and rotation about its normal
(board z). Left free they make the information matrix singular; the clc seed pulls all six
DOFs weakly (r/100 rad, t/10000 m), which also biases the observed plane a little. This
prior pulls ONLY the three in-plane DOFs toward a nominal pose (the seed's board pose),
weakly, leaving the plane (normal and offset) entirely to the data.

It is GTSAM's PriorFactorPose3 with per-direction sigmas in the tangent [omega, v] of the
board frame: omega_z and v_x, v_y get ``sigma_rad`` / ``sigma_m``; the other three get an
infinite sigma (zero information).

SYNOPSIS
    f = board_prior_factor(B(7), T_lidar0_board_seed, sigma_rad=100.0, sigma_m=1e4)
"""

from __future__ import annotations

import numpy as np

# Zero information for the plane's own DOFs (omega_x, omega_y, v_z): a huge sigma.
_FREE = 1e8


def board_prior_factor(board_key: int, T_lidar0_board_nominal, sigma_rad: float, sigma_m: float):
    """Weak prior on the in-plane DOFs (yaw about the normal, in-plane x, y) of a LIDAR-only board."""
    import gtsam

    sigmas = np.array([_FREE, _FREE, sigma_rad, sigma_m, sigma_m, _FREE], dtype=float)
    return gtsam.PriorFactorPose3(board_key, T_lidar0_board_nominal, gtsam.noiseModel.Diagonal.Sigmas(sigmas))
