"""What every command shares: --config / --set, -v / -q (before or after the command name),
--force, range-checked flags, and the config loading that names the flag a bad value came from."""

from __future__ import annotations

import argparse


def verbosity_args(p, *, top: bool = False) -> None:
    """-v/--verbose and -q/--quiet; on a subcommand they default to "not given" so that the same
    flag before the command name is not undone."""
    default = {} if top else {"default": argparse.SUPPRESS}
    p.add_argument("--verbose", "-v", action="store_true", help="debug logging; tracebacks on errors", **default)
    p.add_argument("--quiet", "-q", action="store_true",
                   help="only warnings and errors, no progress (the default when stderr is not a terminal)", **default)


def add_command(sub, name: str, *, run, overrides=None, **kwargs):
    """A subcommand parser with -v/-q; ``run(args) -> exit code`` is called by main."""
    p = sub.add_parser(name, **kwargs)
    verbosity_args(p)
    p.set_defaults(func=run, **({"overrides": overrides} if overrides else {}))
    return p


def config_args(p, config_help: str = "settings (see `clcgraph config dump`)") -> None:
    """--config FILE and --set SECTION.KEY=VALUE, the same on every command that has a config
    (read by ``load_config``)."""
    p.add_argument("--config", default=None, metavar="FILE.yaml", help=config_help)
    p.add_argument("--set", action="append", metavar="SECTION.KEY=VALUE",
                   help="override one config key, after --config and the command's flags (repeatable)")


def load_config(args):
    """Config from --config, then the command's own flags, then --set KEY=VALUE (last wins)."""
    import yaml

    from ..config import Config, ConfigError
    from ..errors import InputError

    try:
        overrides: dict = {}
        cfg = Config.from_yaml(args.config) if getattr(args, "config", None) else Config()
        for section, key, value in getattr(args, "overrides", lambda a: [])(args):
            overrides.setdefault(section, {})[key] = value
        for item in getattr(args, "set", None) or []:
            name, sep, value = item.partition("=")
            section, dot, key = name.partition(".")
            if not sep or not dot:
                raise InputError(f"--set {item!r}: expected SECTION.KEY=VALUE, e.g. solve.outlier_sigma=5")
            try:
                overrides.setdefault(section, {})[key] = yaml.safe_load(value)
            except yaml.YAMLError as e:
                raise InputError(f"--set {item!r}: the value is not YAML ({getattr(e, 'problem', None) or e})") from None
        return cfg.replace(**overrides) if overrides else cfg
    except ConfigError as e:
        key = getattr(e, "key", None)
        flags = [f"--set {item}" for item in getattr(args, "set", None) or [] if item.partition("=")[0] == key]
        section, _, name = (key or "").partition(".")
        if not flags and name in overrides.get(section, {}):  # set by one of the command's flags
            flags = [FLAG_OF.get(key, "--" + name.replace("_", "-"))]
        raise InputError(f"{flags[-1]}: {e}" if flags else str(e)) from None


# config keys set by a differently named flag of `clcgraph solve` (section flags are named after their keys)
FLAG_OF = {
    "snapshots.exclude_bag": "--exclude-bag", "snapshots.decimation_period_s": "--decimation-period",
    "snapshots.max_time_spread_s": "--max-time-spread-s", "sectors.n_sectors": "--Nsectors",
    "sectors.threshold_valid_lidar_range_m": "--threshold-valid-lidar-range",
    "sectors.threshold_valid_lidar_npoints": "--threshold-valid-lidar-Npoints",
    "sectors.uncertainty_quantification_range_m": "--uncertainty-quantification-range",
    "sectors.rt_vehicle_lidar0": "--rt-vehicle-lidar0", "solve.prior_from_tf_static_sigma_rad": "--prior-from-tf-static",
    "solve.prior_from_tf_static_sigma_m": "--prior-from-tf-static",
    "segmentation.debug_region": "--debug-region",
}


def in_range(value, flag: str, lo, hi, *, low_open: bool = False):
    """``value`` of a command-line flag, or InputError naming the flag and its range [lo, hi]
    ((lo, hi] when ``low_open``); NaN and inf are outside every range."""
    import math

    from ..errors import InputError

    ok = math.isfinite(value) and (value > lo if low_open else value >= lo) and value <= hi
    if not ok:
        raise InputError(f"{flag} {value!r}: must be in {'(' if low_open else '['}{lo}, {hi}]")
    return value


def floats(text: str, n: int, flag: str) -> list:
    from ..errors import InputError

    try:
        v = [float(x) for x in text.split(",")]
    except ValueError:
        v = []
    if len(v) != n:
        raise InputError(f"{flag} {text!r}: expected {n} comma-separated numbers")
    return v


def topics_list(text: str) -> list[str]:
    """A comma-separated topic list, blanks dropped."""
    return [t.strip() for t in text.split(",") if t.strip()]


def add_force(p) -> None:
    p.add_argument("--force", action="store_true",
                   help="replace --out even if it is not a previous clcgraph output of this command (its contents "
                        "are deleted); without it, --out must be new, empty or such an output")


def section_flags(p, section_cls, section: str, group_title: str):
    """One --flag per field of a config section (names follow the config keys)."""
    import dataclasses
    import typing

    g = p.add_argument_group(group_title, f"override config '{section}' keys (see `clcgraph config dump`)")
    hints = typing.get_type_hints(section_cls)
    flags = []
    for f in dataclasses.fields(section_cls):
        tp = hints[f.name]
        base = next((a for a in typing.get_args(tp) if a is not type(None)), tp)
        if base is bool or base is list or typing.get_origin(base) is list:
            continue
        dest = f"{section}__{f.name}"
        g.add_argument("--" + f.name.replace("_", "-"), dest=dest, type=base, default=None, metavar=f.name.upper())
        flags.append((dest, section, f.name))
    return flags


def section_overrides(args, flags) -> list:
    """(section, key, value) of the section flags that were given."""
    return [(s, k, getattr(args, d)) for d, s, k in flags if getattr(args, d) is not None]
