"""Monte Carlo with independent noise only, default settings (``python -m bench.mc_independent
[TRIALS_PER_RIG]``, default 34: 102 trials over the three rigs of bench_uncertainty).

No blanket inflation: the sigmas should be no more than 1.3x the Monte-Carlo spread per axis.
The default consider terms (board flatness 1 mm, ring range bias 1 cm, ring elevation 0.1 deg)
describe errors these simulated sensors do not have, so they inflate the sigmas by design; the
table's last column gives by how much (the sigma along each axis over the model part's alone,
exact per trial), the "sigma/spread" column what the Monte Carlo sees.
"""

from bench.mc_run import monte_carlo, trials_from_argv


def main() -> str:
    return monte_carlo("independent", ("independent", True), trials_from_argv(34))


if __name__ == "__main__":
    print(main())
