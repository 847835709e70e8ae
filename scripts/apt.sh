# Sourced by the set-up scripts: apt_install WHO PACKAGE... installs the Debian packages (as root, or through
# sudo), quietly; WHO names the script in its messages. Nothing to do without packages.
apt_install() {
  local who=$1; shift
  [ $# -gt 0 ] || return 0
  echo "$who: installing Debian packages: $*" >&2
  local sudo=""
  if [ "$(id -u)" != 0 ]; then
    command -v sudo >/dev/null 2>&1 || { echo "$who: need root (or sudo) to apt-get install $*" >&2; exit 1; }
    sudo=sudo
  fi
  $sudo apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq --no-install-recommends "$@" >/dev/null
}
