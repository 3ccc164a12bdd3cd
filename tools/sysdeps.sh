#!/bin/sh
# Installs the system packages that a make target needs (tools/system-packages.txt), or says in one
# line what to install. Usage: tools/sysdeps.sh TARGET [LIST]   (TARGET: test or target-test; LIST: the
# package list, tools/system-packages.txt by default).
#   nothing missing           -> nothing is run, exit 0 (a second `make test` does no apt work)
#   missing, running as root  -> apt-get update; one apt-get install of exactly the missing packages
#   missing, passwordless sudo-> the same through sudo -n
#   otherwise                 -> one line naming the packages and the command to run, exit 2
# A package counts as there when dpkg says so or when its probe (a command or a path) is found. On a
# system without dpkg, what is missing is named in one line, exit 2 (installed by hand).
set -u
target=${1:?usage: tools/sysdeps.sh TARGET [LIST]}
list=${2:-$(dirname "$0")/system-packages.txt}
[ -r "$list" ] || { echo "sysdeps: package list $list is not readable" >&2; exit 2; }

pkgs=$(awk -v t="$target" '$1 !~ /^#/ && NF >= 3 && $2 == t { print $1 }' "$list")
[ -n "$pkgs" ] || exit 0

# a package counts as there when dpkg says it is installed, or when its probe is found (Node.js from
# another source than Debian's, a LinuxCNC built by hand)
have_dpkg=false
command -v dpkg >/dev/null 2>&1 && have_dpkg=true
missing=""
for p in $pkgs; do
  if $have_dpkg && dpkg -s "$p" 2>/dev/null | grep -q '^Status: install ok installed'; then continue; fi
  probe=$(awk -v p="$p" '$1 == p { print $3; exit }' "$list")
  case "$probe" in
    -) $have_dpkg || continue ;;
    /*) ls -d $probe >/dev/null 2>&1 && continue ;;
    *) command -v "$probe" >/dev/null 2>&1 && continue ;;
  esac
  missing="$missing $p"
done
if [ -n "$missing" ] && ! $have_dpkg; then
  echo "make $target needs system packages that are missing (Debian names:$missing); no dpkg here: install their equivalents by hand (README, Two commands)" >&2
  exit 2
fi
[ -n "$missing" ] || exit 0
missing=${missing# }

if [ "$(id -u)" = 0 ]; then
  run=""
elif command -v sudo >/dev/null 2>&1 && sudo -n true >/dev/null 2>&1; then
  run="sudo -n"
else
  echo "make $target needs system packages that are not installed: $missing; run: sudo apt-get install --no-install-recommends $missing" >&2
  exit 2
fi
echo "make $target: installing $missing (apt-get)"
$run env DEBIAN_FRONTEND=noninteractive apt-get update -q || exit 1
# shellcheck disable=SC2086  # one word per package
$run env DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends $missing || exit 1
