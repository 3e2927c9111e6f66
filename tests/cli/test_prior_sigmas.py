"""--prior-from-tf-static SIGMA_RAD,SIGMA_M: one sigma for radians and metres is gone (the old
single value and the old config key are one-line errors that say what to write instead)."""

import numpy as np
import pytest


def test_old_single_prior_sigma_is_a_config_error_with_the_new_keys(capsys):
    from clcgraph.cli import main
    from clcgraph.config import Config, ConfigError

    with pytest.raises(ConfigError, match="prior_from_tf_static_sigma_rad and solve.prior_from_tf_static_sigma_m"):
        Config.from_dict({"solve": {"prior_from_tf_static_sigma": 0.05}})
    cfg = Config.from_dict({"solve": {"prior_from_tf_static_sigma_rad": 0.01, "prior_from_tf_static_sigma_m": 0.05}})
    assert (cfg.solve.prior_from_tf_static_sigma_rad, cfg.solve.prior_from_tf_static_sigma_m) == (0.01, 0.05)
    assert main(["config", "check", "--set", "solve.prior_from_tf_static_sigma=0.05"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "prior_from_tf_static_sigma_rad" in err[0], err


def test_prior_from_tf_static_takes_two_sigmas(tmp_path, capsys, bag_factory):
    from clcgraph.api import _tf_priors
    from clcgraph.cli import main
    from clcgraph.types import Sensor

    bag = bag_factory(tmp_path / "b.bag", camera=None)
    sensors = [Sensor(topic="/lidar0", kind="lidar"), Sensor(topic="/lidar1", kind="lidar")]
    (prior,) = _tf_priors([bag], sensors, 0.01, 0.05)
    np.testing.assert_array_equal(prior.sigma_rt, [0.01] * 3 + [0.05] * 3)
    np.testing.assert_allclose(prior.rt_lidar0_sensor, [0, 0, 0.1, 0.5, 0, 0], atol=1e-12)
    rc = main(["solve", "--bag", str(bag), "--topics", "/lidar0,/lidar1", "--out", str(tmp_path / "o"),
               "--prior-from-tf-static", "0.05"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "SIGMA_RAD,SIGMA_M" in err[0], err
    assert not (tmp_path / "o").exists()
