"""Monte Carlo with every correlated error of issue 12 (``python -m bench.mc_correlated [TRIALS_PER_RIG]``,
default 68: 204 trials over the three rigs of bench_uncertainty).

The simulated captures carry per-ring range bias (2 cm) and elevation error (0.1 deg), taken out
by the frontend's per-ring correction as `clcgraph solve` does; a 3 mm board bow, mixed pixels
(3 cm) at the board's edges, a per-board corner bias (0.2 px) and a lens-model field (0.3 px);
plus independent noise. The solve states the sensors' and the board's errors as a user states
theirs (board flatness 3 mm, ring range bias 2 cm, ring elevation 0.1 deg, lens field 0.3 px).
Goal per (rig, sensor, axis): >= 95 % of |z| <= 3 and mean z^2 in 0.7-1.5.
"""

from bench.mc_run import monte_carlo, trials_from_argv

SETTINGS = ("board_flatness_m=0.003 lidar_ring_range_bias_m=0.02 lidar_ring_elevation_deg=0.1 "
            "camera_lens_field_px=0.3")
# the consistency check does not yet know the terms (a capture it refuses is still a sample); nor is
# one whose sigma the terms make too large to use (solve.max_stdev_m, 3 cm: 130 of 204 trials here):
# kept out, they would leave only the precise trials. 10 cm / 3 deg, the limits before it, keep
# the undetermined ones out
SETTINGS_UNREFUSED = SETTINGS + " refuse_inconsistent=0 max_stdev_m=0.1 max_stdev_deg=3"


def main() -> str:
    return monte_carlo("correlated", ("all", True), trials_from_argv(68), SETTINGS_UNREFUSED)


if __name__ == "__main__":
    print(main())
