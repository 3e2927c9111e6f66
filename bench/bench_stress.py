"""The stress set (bench/stress.py) as a benchmark: every capture through the CLI with default
settings; the table shows outcome, error, sigma and |z| per capture."""

from __future__ import annotations


def main() -> str:
    from bench import stress

    return stress.main([])
