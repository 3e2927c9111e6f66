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


def test_board_section_round_trip(tmp_path):
    """The board as people measure it: corners, square, physical size, pattern offset."""
    p = tmp_path / "c.yaml"
    p.write_text("board:\n  corners: [7, 5]\n  square_m: 0.095\n  size_m: [0.85, 0.61]\n"
                 "  pattern_offset_m: [0.01, -0.005]\n")
    c = Config.from_yaml(p)
    assert c.board.corners == [7, 5] and c.board.size_m == [0.85, 0.61]
    assert c.board.pattern_offset_m == [0.01, -0.005] and c.detection.detector == "auto"
    for comments in (False, True):
        p.write_text(c.to_yaml(comments=comments))
        assert Config.from_yaml(p) == c
    assert Config().board.size_m == [1.3, 1.3] and Config().board.corners == [10, 10]


def test_board_keys_validated():
    with pytest.raises(ConfigError, match=r"'board.corners' must be two integers"):
        Config.from_dict({"board": {"corners": [7.5, 5]}})
    with pytest.raises(ConfigError, match=r"'board.size_m' must be two numbers"):
        Config.from_dict({"board": {"size_m": [1.3]}})
    with pytest.raises(ConfigError, match=r"'board.square_m' must be positive"):
        Config.from_dict({"board": {"square_m": 0}})
    # the 1.1 m pattern of the default board does not fit on 1.1 m minus an offset
    with pytest.raises(ConfigError, match=r"'board.size_m': the pattern \(11 squares of 0.1 m = 1.100 m along the "
                                          r"width, offset 0.05 m\) does not fit on a 1.1 m width"):
        Config.from_dict({"board": {"size_m": [1.1, 1.3], "pattern_offset_m": [0.05, 0]}})
    with pytest.raises(ConfigError, match="'detection.detector' must be one of auto, mrgingham, opencv"):
        Config.from_dict({"detection": {"detector": "zhang"}})


@pytest.mark.parametrize("key", ["corners_x", "corners_y", "spacing_m", "margin_m"])
def test_old_board_keys_point_to_the_board_section(key):
    with pytest.raises(ConfigError) as e:
        Config.from_dict({"detection": {key: 1}})
    msg = str(e.value)
    assert msg.startswith(f"'detection.{key}' moved to the 'board' section") and "\n" not in msg
    assert "board: {corners: [nx, ny], square_m: s, size_m: [width, height]}" in msg
    with pytest.raises(ConfigError, match=f"'detection.{key}' moved to the 'board' section"):
        Config().replace(detection={key: 1})  # --set detection.KEY=... takes this path
