#!/usr/bin/env bash
# Run a command as if some real components were not installed, to see what strict CI does
# without them (README, "Tests and mutation testing"). Needs root (or a user namespace with
# mount rights); changes nothing outside a private mount namespace.
#
#   tests/run_without.sh bwrap,postgresql,chromium -- env CI=true .venv/bin/pytest tests/...
#
# bwrap and chromium are removed from /usr/bin through an overlay (whiteouts on a tmpfs);
# postgresql hides /usr/lib/postgresql under an empty tmpfs.
set -euo pipefail
if [ $# -lt 3 ] || [ "$2" != "--" ]; then
  echo "usage: $0 bwrap,postgresql,chromium -- COMMAND..." >&2
  exit 2
fi
hide=$1
shift 2
exec unshare --mount --propagation private bash -euo pipefail -c '
  hide=$1; shift
  scratch=$(mktemp -d)
  mount -t tmpfs slipstream-hide "$scratch"
  mkdir "$scratch/upper" "$scratch/work"
  mount -t overlay overlay \
    -o "lowerdir=/usr/bin,upperdir=$scratch/upper,workdir=$scratch/work" /usr/bin
  for name in ${hide//,/ }; do
    case $name in
      bwrap|chromium) rm -f "/usr/bin/$name" ;;
      postgresql) mount -t tmpfs slipstream-hide /usr/lib/postgresql ;;
      *) echo "run_without.sh: cannot hide $name (bwrap, postgresql, chromium)" >&2; exit 2 ;;
    esac
  done
  exec "$@"
' run_without "$hide" "$@"
