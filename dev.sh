#!/usr/bin/env bash
# The one entry point: sets everything up on a fresh Debian 12 (idempotent, fast once done),
# then runs the requested job.
#   ./dev.sh demo     simulate the demo data if missing, then calibrate it
#   ./dev.sh test     the test suite (what CI runs)
#   ./dev.sh bench    benchmarks, printed as tables
#   ./dev.sh setup    only the set-up
set -euo pipefail
cd "$(dirname "$0")"

APT_PACKAGES=(python3-mrcal mrgingham python3-venv python3-matplotlib python3-scipy python3-yaml)
VENV=.venv
STAMP="$VENV/.clcgraph-installed"

as_root() { if [ "$(id -u)" = 0 ]; then "$@"; else sudo "$@"; fi; }

setup() {
    local missing=()
    for p in "${APT_PACKAGES[@]}"; do
        dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "ok installed" || missing+=("$p")
    done
    if [ ${#missing[@]} -gt 0 ]; then
        echo "dev.sh: installing Debian packages: ${missing[*]}" >&2
        as_root apt-get update -q
        DEBIAN_FRONTEND=noninteractive as_root apt-get install -y -q --no-install-recommends "${missing[@]}"
    fi
    # Re-install when pyproject.toml changes; otherwise this is a no-op.
    local want; want=$(sha256sum pyproject.toml | cut -d' ' -f1)
    if [ ! -x "$VENV/bin/python" ] || [ "$(cat "$STAMP" 2>/dev/null)" != "$want" ]; then
        echo "dev.sh: creating $VENV (system site packages, for Debian's mrcal)" >&2
        [ -x "$VENV/bin/python" ] || /usr/bin/python3 -m venv --system-site-packages "$VENV"
        "$VENV/bin/python" -m pip install -q --disable-pip-version-check -e ".[test,fleet]"
        echo "$want" > "$STAMP"
    fi
}

setup
case "${1:-}" in
    setup) ;;
    demo) shift; exec "$VENV/bin/clcgraph" demo "$@" ;;
    test) shift; exec "$VENV/bin/python" -m pytest -n 2 "$@" ;;
    bench) shift; exec "$VENV/bin/python" -m bench "$@" ;;
    *) echo "usage: ./dev.sh {demo|test|bench|setup} [args...]" >&2; exit 2 ;;
esac
