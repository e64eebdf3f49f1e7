#!/bin/bash
# guest-launch.sh: starts the user's command inside the UML guest (run by guest-init.sh as
#   env -i bash guest-launch.sh ENV_FILE ARGV_FILE CWD
# under `timeout`). run-in-vcan.sh copies it into the results directory as launch.sh.
#
# ENV_FILE  `export NAME=VALUE` lines (values quoted with printf %q) generated from the caller's
#           exported environment (RUST_LOG, RUST_BACKTRACE, CARGO_TARGET_DIR, PATH, HOME, ...).
# ARGV_FILE the command and its arguments, NUL-separated (survives any quoting/whitespace).
# CWD       the caller's working directory (seen read-only through hostfs unless overlaid/--rw).
#
# Exit code: the command's own (exec), 127 if it is not found, 125 if the launch itself fails.
set -uo pipefail

envf=$1 argvf=$2 cwd=$3

# shellcheck source=/dev/null
source "$envf" || { echo "[hil-guest] cannot source $envf" >&2; exit 125; }

# Sane defaults on top of what the caller passed through.
sysdirs=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin
export PATH=${PATH:+$PATH:}$sysdirs
export HOME=${HOME:-/root}
export HIL_IN_GUEST=1 HIL_MODE=uml
# TMPDIR must be writable: the host's value may point into the read-only root.
if [[ -n ${TMPDIR:-} && ! -w ${TMPDIR} ]]; then export TMPDIR=/tmp; fi

cd -- "$cwd" || { echo "[hil-guest] cannot cd to $cwd inside the guest" >&2; exit 125; }

mapfile -d '' -t argv < "$argvf"
((${#argv[@]})) || { echo "[hil-guest] empty command" >&2; exit 125; }
exec "${argv[@]}"
