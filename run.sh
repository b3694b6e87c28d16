#!/usr/bin/env bash
# Set-up and entry point: installs what a fresh Debian machine lacks, then runs a job.
#   ./run.sh            render the built-in demo scene (the paper's Cheese) to cheese.exr / cheese.png
#   ./run.sh test       run the test suite
#   ./run.sh bench ...  run a benchmark script from benchmarks/
#   ./run.sh -- CMD     run CMD inside the project's virtual environment
set -euo pipefail
cd "$(dirname "$0")"
root=$(pwd)

as_root() { if [ "$(id -u)" -eq 0 ]; then "$@"; else sudo "$@"; fi; }

# ---- System packages (Debian): Python, and the LLVM that Dr.Jit's CPU backend loads ----
need=()
command -v python3 >/dev/null || need+=(python3)
python3 -c 'import venv, ensurepip' 2>/dev/null || need+=(python3-venv)
# Dr.Jit 1.5 fails with LLVM 15 ('Cannot select fminimum'); Debian 12's libllvm19 works.
ls /usr/lib/x86_64-linux-gnu/libLLVM-19.so* /usr/lib/*/libLLVM*19*.so* >/dev/null 2>&1 || need+=(libllvm19)
if [ ${#need[@]} -gt 0 ]; then
    echo "run.sh: installing system packages: ${need[*]}" >&2
    as_root apt-get update -qq
    DEBIAN_FRONTEND=noninteractive as_root apt-get install -y -qq "${need[@]}" >/dev/null
fi
llvm=$(ls /usr/lib/*/libLLVM-19.so* /usr/lib/*/libLLVM.so.19* 2>/dev/null | head -n 1 || true)
if [ -n "$llvm" ]; then export DRJIT_LIBLLVM_PATH="$llvm"; fi

# ---- Python environment (a venv in .venv, reinstalled when pyproject.toml changes) ----
venv="$root/.venv"
[ -x "$venv/bin/python" ] || python3 -m venv "$venv"
stamp="$venv/.installed-$(sha1sum pyproject.toml | cut -c1-12)"
if [ ! -f "$stamp" ]; then
    echo "run.sh: installing Python packages into .venv" >&2
    "$venv/bin/python" -m pip install -q --upgrade pip >/dev/null
    "$venv/bin/python" -m pip install -q -e ".[test,bench,distributed]"
    rm -f "$venv"/.installed-*
    touch "$stamp"
fi
py="$venv/bin/python"

# The OpenSCAD tests compare with OpenSCAD's own exports of its bundled examples.
if [ "${1:-demo}" = "test" ] && ! command -v openscad >/dev/null; then
    echo "run.sh: installing openscad (reference data for the tests)" >&2
    as_root apt-get update -qq
    DEBIAN_FRONTEND=noninteractive as_root apt-get install -y -qq --no-install-recommends openscad >/dev/null
fi

# ---- The job ----
job=${1:-demo}
[ $# -gt 0 ] && shift
case "$job" in
    demo)  exec "$py" -m mitsuba_csg render --png "$@" ;;
    test)  exec "$py" -m pytest "$@" ;;
    bench) script=$1; shift; exec "$py" "benchmarks/$script" "$@" ;;
    --)    exec "$venv/bin/$1" "${@:2}" ;;
    *)     echo "run.sh: unknown job '$job' (use: demo, test, bench SCRIPT, -- CMD)" >&2; exit 2 ;;
esac
