"""The `clcgraph` subcommands on real (written) bags: what they print and draw."""

from clcgraph.cli import main


def test_show_bag_previews(capsys, tmp_path, good):
    assert main(["show-bag", str(good), "--png", str(tmp_path / "png")]) == 0
    out = capsys.readouterr().out
    assert "/lidar0" in out and "PointCloud2 1 x 5760" in out
    names = sorted(p.name for p in (tmp_path / "png").iterdir())
    assert names == ["good_cam0.png", "good_lidar0.png", "good_lidar1.png"]
    import matplotlib.image

    assert matplotlib.image.imread(tmp_path / "png" / "good_lidar0.png").shape[1] > 600
