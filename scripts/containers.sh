#!/usr/bin/env bash
# Containers on a host without Docker and without a reachable image registry: podman from Debian,
# a local base image made with debootstrap, the project image built with the host's own pip indexes.
#
#   scripts/containers.sh setup    podman, runc, netavark, podman-compose (pinned, own venv), podman's
#                                  containers.conf, the base image localhost/eqa-base:bookworm and the Redis
#                                  image localhost/eqa-redis:7 (idempotent; a second run changes nothing)
#   scripts/containers.sh build    the project image eqa:latest from ./Dockerfile (layer cache: warm is quick)
#   scripts/containers.sh compose ARGS...   podman-compose with docker-compose.yml + docker-compose.podman.yml
#
# Every change to the host is printed at the end ("changed on this host: ..."). Needs root (or sudo) for apt,
# /etc/containers and rootful podman. Nothing here is needed where Docker and a registry are available:
# there, `docker compose up` uses docker-compose.yml alone.
set -euo pipefail
cd "$(dirname "$0")/.."

PODMAN_COMPOSE_VERSION=1.6.0           # PyPI; Debian bookworm's 1.0.3 ignores deploy.replicas and !override
STATE=${EQA_CONTAINERS_DIR:-/var/cache/eqa-containers}   # rootfs of the base image, podman-compose venv
SUITE=bookworm
BASE_IMAGE=localhost/eqa-base:$SUITE
REDIS_IMAGE=localhost/eqa-redis:7
IMAGE=localhost/eqa:latest
CONF=/etc/containers/containers.conf
MARK="# Written by scripts/containers.sh (eqa)"
CHANGED=()

SUDO=""
if [ "$(id -u)" != 0 ]; then
  command -v sudo >/dev/null 2>&1 || { echo "containers: need root (or sudo) for apt and rootful podman" >&2; exit 1; }
  SUDO=sudo
fi

say() { echo "containers: $*"; }
changed() { CHANGED+=("$1"); say "changed: $1"; }
report() {
  if [ ${#CHANGED[@]} -eq 0 ]; then say "nothing changed on this host"
  else say "changed on this host:"; printf '  - %s\n' "${CHANGED[@]}"; fi
}

# The Debian mirror the host's apt uses (deb822 or one-line sources), for debootstrap.
debian_mirror() {
  local m
  m=$(grep -hs -E '^(URIs:|deb )' /etc/apt/sources.list.d/*.sources /etc/apt/sources.list /etc/apt/sources.list.d/*.list \
      | grep -E '/debian/?( |$)' | grep -v security | head -1 | sed -E 's/^URIs: *//; s/^deb (\[[^]]*\] )?//; s/ .*//')
  echo "${m:-http://deb.debian.org/debian}"
}

setup_packages() {
  local want=(podman runc netavark aardvark-dns slirp4netns uidmap fuse-overlayfs containernetworking-plugins
              iptables debootstrap python3-venv) missing=() p
  for p in "${want[@]}"; do
    dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
  done
  if [ ${#missing[@]} -gt 0 ]; then
    say "installing Debian packages: ${missing[*]}"
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
    changed "apt-get install ${missing[*]}"
  fi
}

setup_conf() {
  # crun fails here ("cgroups in hybrid mode not supported", then setrlimit EPERM); runc with the cgroupfs
  # manager and no default ulimits runs containers. No systemd as PID 1: events to a file.
  local want
  want=$(cat <<EOF
$MARK: crun cannot run containers on this host
# ("cgroups in hybrid mode not supported", setrlimit not permitted); runc with cgroupfs can.
[containers]
default_ulimits = []

[engine]
runtime = "runc"
cgroup_manager = "cgroupfs"
events_logger = "file"

[network]
network_backend = "netavark"
EOF
)
  if [ -f "$CONF" ] && [ "$(cat "$CONF")" = "$want" ]; then return; fi
  if [ -f "$CONF" ] && ! grep -qF "$MARK" "$CONF"; then
    $SUDO cp "$CONF" "$CONF.before-eqa"
    changed "saved the previous $CONF as $CONF.before-eqa"
  fi
  echo "$want" | $SUDO tee "$CONF" >/dev/null
  changed "wrote $CONF (runtime runc, cgroupfs, default_ulimits = [], netavark)"
}

setup_compose() {
  local venv=$STATE/venv
  if [ -x "$venv/bin/podman-compose" ] && \
     [ "$("$venv/bin/python" -m pip show podman-compose 2>/dev/null | sed -n 's/^Version: //p')" = "$PODMAN_COMPOSE_VERSION" ]; then
    return
  fi
  $SUDO mkdir -p "$STATE"
  [ -x "$venv/bin/python" ] || $SUDO python3 -m venv "$venv"
  $SUDO "$venv/bin/python" -m pip install -q "podman-compose==$PODMAN_COMPOSE_VERSION" 2>&1 | grep -v '^WARNING: Location' || true
  "$venv/bin/podman-compose" --version >/dev/null
  changed "installed podman-compose $PODMAN_COMPOSE_VERSION in $venv"
}

image_exists() { $SUDO podman image exists "$1"; }

setup_base() {
  image_exists "$BASE_IMAGE" && return
  local root=$STATE/rootfs-$SUITE mirror
  mirror=$(debian_mirror)
  if [ ! -x "$root/usr/bin/python3" ]; then
    say "debootstrap $SUITE from $mirror into $root (slow: a few minutes)"
    $SUDO rm -rf "$root.tmp"
    $SUDO mkdir -p "$STATE"
    $SUDO debootstrap --variant=minbase --include=python3,python3-venv,ca-certificates "$SUITE" "$root.tmp" "$mirror" \
      > "$STATE/debootstrap.log" 2>&1 || { tail -20 "$STATE/debootstrap.log" >&2; exit 1; }
    $SUDO mv "$root.tmp" "$root"
    changed "debootstrap of Debian $SUITE in $root"
  fi
  $SUDO rm -rf "$root/var/cache/apt/archives/"*.deb "$root/var/lib/apt/lists/"* || true
  $SUDO tar -C "$root" -c . | $SUDO podman import --change 'CMD ["/bin/bash"]' --change 'ENV LANG=C.UTF-8' \
    - "$BASE_IMAGE" >/dev/null
  changed "podman image $BASE_IMAGE (imported from $root)"
}

# podman build options that give a build the host's network, pip configuration, wheel directories, local
# indexes and CA bundle (mounted read-only at the same paths, so the configuration's paths stay valid).
build_opts() {
  local conf=$STATE/pip.conf paths=() p
  $SUDO mkdir -p "$STATE"
  # `pip config list` prints the effective settings of all pip files and PIP_* variables (key='value');
  # one [global] file of them, a variable winning over a file as in pip.
  "$STATE/venv/bin/python" -m pip config list 2>/dev/null | "$STATE/venv/bin/python" -c '
import re, sys
seen = {}
for line in sys.stdin:
    m = re.match(r"^([^.]*)\.([a-z0-9-]+)=(.*)$", line.strip())
    if m and (m.group(1) == ":env:" or m.group(2) not in seen):
        seen[m.group(2)] = m.group(3).strip("\x27\"")
print("[global]")
for k, v in sorted(seen.items()):
    print(f"{k} = {v}")
' | $SUDO tee "$conf.new" >/dev/null
  if ! cmp -s "$conf.new" "$conf"; then $SUDO mv "$conf.new" "$conf"; else $SUDO rm -f "$conf.new"; fi
  # A local index (file://.../simple) links its files relative to itself (../../files/...): mount its parent.
  for p in $(sed -n -E 's/^[a-z-]+ = //p' "$conf" | tr ' ' '\n' \
             | sed -E 's#^file://(.*)/simple/?$#\1#; s#^file://##'); do
    case "$p" in /*) [ -e "$p" ] && paths+=("$p") ;; esac
  done
  BUILD_OPTS=(--network host -v "$conf:/etc/pip.conf:ro")
  for p in $(printf '%s\n' "${paths[@]}" | sort -u); do BUILD_OPTS+=(-v "$p:$p:ro"); done
}

setup_redis() {
  image_exists "$REDIS_IMAGE" && return
  local dir
  dir=$(mktemp -d)
  cat > "$dir/Containerfile" <<EOF
FROM $BASE_IMAGE
RUN apt-get update && apt-get install -y --no-install-recommends redis-server && rm -rf /var/lib/apt/lists/*
EXPOSE 6379
CMD ["redis-server", "--protected-mode", "no"]
EOF
  $SUDO podman build --network host -q -t "$REDIS_IMAGE" "$dir" >/dev/null
  rm -rf "$dir"
  changed "podman image $REDIS_IMAGE (Debian's redis-server on $BASE_IMAGE)"
}

cmd_setup() {
  setup_packages
  setup_conf
  setup_compose
  setup_base
  setup_redis
  report
}

cmd_build() {
  image_exists "$BASE_IMAGE" || { echo "containers: no $BASE_IMAGE: run scripts/containers.sh setup first" >&2; exit 1; }
  build_opts
  local t0 t1 before after
  before=$($SUDO podman image inspect -f '{{.Id}}' "$IMAGE" 2>/dev/null || true)
  t0=$(date +%s)
  $SUDO podman build "${BUILD_OPTS[@]}" --build-arg "BASE=$BASE_IMAGE" --build-arg TORCH_INDEX= \
    --layers -t "$IMAGE" -f Dockerfile . >&2
  t1=$(date +%s)
  after=$($SUDO podman image inspect -f '{{.Id}}' "$IMAGE")
  say "built $IMAGE in $((t1 - t0)) s, $($SUDO podman image inspect -f '{{.Size}}' "$IMAGE" | awk '{printf "%.2f GB", $1/1e9}')"
  [ "$before" = "$after" ] || changed "podman image $IMAGE"
  report
}

cmd_compose() {
  $SUDO "$STATE/venv/bin/podman-compose" -f docker-compose.yml -f docker-compose.podman.yml "$@"
}

case "${1:-setup}" in
  setup) cmd_setup ;;
  build) cmd_build ;;
  compose) shift; cmd_compose "$@" ;;
  -h|--help|help) sed -n '2,/^set /p' "$0" | grep '^#' | sed 's/^# \{0,1\}//' ;;
  *) echo "containers: unknown command '$1' (setup, build, compose ARGS..., --help)" >&2; exit 2 ;;
esac
