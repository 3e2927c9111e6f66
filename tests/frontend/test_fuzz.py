"""Decoders fed randomly mutated real messages (bench/bench_fuzz.py runs 10^5 of these):
a decoded message or a DataError, nothing else, within 1 s and a few times the message's memory."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository's bench/ package

from bench import bench_fuzz  # noqa: E402


def test_mutated_messages_give_only_dataerrors(tmp_path, capfd):
    samples = bench_fuzz.sample_messages(tmp_path)
    assert {s.msgtype.rsplit("/", 1)[1] for s in samples[0]} == {"PointCloud2", "Image", "CompressedImage",
                                                                  "TFMessage"}
    tallies = bench_fuzz.run(3000, seed=7, samples=samples)
    report = bench_fuzz.table(tallies)
    for kind, t in tallies.items():
        assert t.other == 0 and t.slow == 0 and t.over_memory == 0, report
        # the mutations reach the decoders: some decode, some are refused by them
        assert t.data_errors > 0, (kind, report)
        assert t.decoded + t.data_errors + t.undeserializable == t.cases
    assert sum(t.decoded for t in tallies.values()) > 500, report
    assert capfd.readouterr().err == ""  # no codec chatter, no warnings
