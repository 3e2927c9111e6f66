import pytest

from clcgraph.config import Config, ConfigError


def test_defaults_round_trip(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text(Config().to_yaml())
    assert Config.from_yaml(p) == Config()
    p.write_text(Config().to_yaml(comments=True))
    assert Config.from_yaml(p) == Config()


def test_commented_dump_documents_fields():
    text = Config().to_yaml(comments=True)
    # the comment above a field in config.py lands above its key
    i = text.index("  outlier_sigma:")
    assert "# Outliers" in text[text.rfind("\n", 0, i - 2) - 200 : i]
    assert text.count("\n  #") > 30


def test_unknown_key_is_named(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("solve:\n  outlier_sigmaa: 3\n")
    with pytest.raises(ConfigError, match=r"c.yaml: unknown config key 'solve.outlier_sigmaa'"):
        Config.from_yaml(p)
    with pytest.raises(ConfigError, match="unknown config key 'nope'"):
        Config.from_dict({"nope": {}})


def test_types_are_checked_not_fixed():
    with pytest.raises(ConfigError, match="'segmentation.min_rings' must be an integer"):
        Config.from_dict({"segmentation": {"min_rings": 2.5}})
    with pytest.raises(ConfigError, match="'solve.reject_outliers' must be true or false"):
        Config.from_dict({"solve": {"reject_outliers": "yes"}})
    c = Config.from_dict({"snapshots": {"decimation_period_s": 2}})
    assert c.snapshots.decimation_period_s == 2.0
    assert Config().replace(solve={"outlier_sigma": 3}).solve.outlier_sigma == 3.0
