#!/usr/bin/env bash
# Builds the pointfarm image from deploy/container/Containerfile (the multi-stage build: the
# release binary compiled in a Debian builder stage, a runtime stage with Mesa's lavapipe) with
# podman or docker, then runs the demo inside it: a daemon and its worker in one container
# render a 12-frame turntable of a generated sample cloud on lavapipe, into
# target/container-demo/ on this machine, and the script checks the 12 frames are there.
#
#   bash deploy/container/build.sh               # build, run the demo; fails without an engine
#   bash deploy/container/build.sh --if-engine   # the same, but without a working container
#                                                # engine say so and succeed (what test.sh runs)
#   bash deploy/container/build.sh --no-demo     # build only
#   bash deploy/container/build.sh --binary target/release/pointfarm
#       # the runtime stage around a binary built on this machine (a Debian 12 one, or an
#       # older glibc) instead of the builder stage's: the same image in a minute, for a
#       # machine that has just built the binary anyway
#
# Environment:
#   POINTFARM_IMAGE             the tag to build (default localhost/pointfarm:latest)
#   POINTFARM_CONTAINER_ENGINE  podman or docker (default: the first of them that works here)
#   POINTFARM_BASE_IMAGE        the Debian 12 image both stages start from. Default: the image
#                               localhost/pointfarm-base:bookworm, made here when missing from
#                               Debian packages with mmdebstrap (from the mirrors this
#                               machine's apt sources name, so no registry is needed); where
#                               that cannot be made, the registry's debian:bookworm-slim.
#   POINTFARM_REBUILD_BASE=1    make localhost/pointfarm-base:bookworm again (newer packages)
#   POINTFARM_MESA=stock        bookworm's own Mesa in the image instead of bookworm-backports'
set -euo pipefail
cd "$(dirname "$0")/../.."

say() { echo "pointfarm container: $*" >&2; }
die() {
    say "$*"
    exit 1
}

if_engine=no
demo=yes
binary=""
while [ $# -gt 0 ]; do
    arg=$1
    shift
    case $arg in
        --if-engine) if_engine=yes ;;
        --no-demo) demo=no ;;
        --binary)
            [ $# -gt 0 ] || die "--binary needs the path of a pointfarm binary"
            binary=$1
            shift
            [ -x "$binary" ] || die "--binary $binary: no executable there"
            ;;
        -h | --help)
            sed -n '2,/^set -euo/p' "$0" | sed '$d; s/^# \{0,1\}//'
            exit 0
            ;;
        *) die "unknown argument $arg (see --help)" ;;
    esac
done

image=${POINTFARM_IMAGE:-localhost/pointfarm:latest}
local_base=localhost/pointfarm-base:bookworm
registry_base=docker.io/library/debian:bookworm-slim

# The engine: one whose daemon or storage answers (the docker CLI alone, with no engine
# behind it, does not count).
engine=""
candidates=(podman docker)
if [ -n "${POINTFARM_CONTAINER_ENGINE:-}" ]; then candidates=("$POINTFARM_CONTAINER_ENGINE"); fi
for candidate in "${candidates[@]}"; do
    if command -v "$candidate" >/dev/null && "$candidate" info >/dev/null 2>&1; then
        engine=$candidate
        break
    fi
done
if [ -z "$engine" ]; then
    message="no container engine works here (${candidates[*]}: not installed, or its 'info' fails)"
    if [ "$if_engine" = yes ]; then
        say "skipping the image build and the demo in it: $message"
        exit 0
    fi
    die "$message; install podman (apt-get install podman) or start docker"
fi
say "engine: $engine ($("$engine" --version 2>/dev/null | head -n 1))"

image_exists() {
    "$engine" image inspect "$1" >/dev/null 2>&1
}

# Prints the "deb URI SUITE main" lines of this machine's apt sources for Debian 12's main,
# updates and security suites (the image's builder needs the security suite's rustc-web), or
# nothing when the machine has no bookworm source.
debian_source_lines() {
    # shellcheck source=deploy/setup.sh
    source deploy/setup.sh
    apt_entries /etc/apt | awk '
        ("," $2 ",") ~ /,deb,/ && $3 !~ /^cdrom:/ &&
        ($4 == "bookworm" || $4 == "bookworm-updates" || $4 == "bookworm-security") &&
        !seen[$4]++ { print "deb " $3 " " $4 " main" }'
}

make_local_base() {
    local lines=()
    mapfile -t lines < <(debian_source_lines)
    if [ ${#lines[@]} -eq 0 ] || ! printf '%s\n' "${lines[@]}" | grep -q ' bookworm-security '; then
        say "this machine's apt sources name no Debian 12 main and security archives to make a base image from"
        return 1
    fi
    say "making $local_base with mmdebstrap from this machine's Debian sources:"
    printf '    %s\n' "${lines[@]}" >&2
    local tarball
    tarball=$(mktemp --suffix=.tar)
    # shellcheck disable=SC2064
    trap "rm -f '$tarball'" EXIT
    local start=$SECONDS
    mmdebstrap --quiet --variant=minbase bookworm "$tarball" "${lines[@]}" ||
        { say "mmdebstrap failed"; return 1; }
    "$engine" import --change 'CMD ["/bin/bash"]' "$tarball" "$local_base" >/dev/null 2>&1 ||
        { say "$engine import failed"; return 1; }
    rm -f "$tarball"
    say "made $local_base in $((SECONDS - start)) s"
}

if [ -n "${POINTFARM_BASE_IMAGE:-}" ]; then
    base=$POINTFARM_BASE_IMAGE
elif image_exists "$local_base" && [ "${POINTFARM_REBUILD_BASE:-}" != 1 ]; then
    base=$local_base
elif command -v mmdebstrap >/dev/null && make_local_base; then
    base=$local_base
else
    say "no local base image (mmdebstrap missing or failed); using the registry's $registry_base"
    base=$registry_base
fi
if ! image_exists "$base"; then
    say "pulling $base"
    if ! "$engine" pull "$base" >/dev/null; then
        message="cannot pull $base, and no base image could be made here (install mmdebstrap, or set POINTFARM_BASE_IMAGE to a Debian 12 image this engine has)"
        if [ "$if_engine" = yes ]; then
            say "skipping the image build and the demo in it: $message"
            exit 0
        fi
        die "$message"
    fi
fi
say "base image: $base"

# How this engine starts containers here. Some hosts need more than the defaults: an engine
# without CAP_SYS_RESOURCE cannot raise a container's open-file and process limits to podman's
# defaults (1048576; podman itself runs with at most 32768 processes), and crun refuses hosts
# whose cgroups are a v1/v2 hybrid where runc does not. The first of these that starts a
# container from the base image is used for the build and the runs.
hard_nofile=$(ulimit -Hn)
hard_nproc=$(ulimit -Hu)
if [ "$hard_nproc" = unlimited ] || [ "$hard_nproc" -gt 32768 ]; then hard_nproc=32768; fi
limits=(--ulimit "nofile=$hard_nofile:$hard_nofile" --ulimit "nproc=$hard_nproc:$hard_nproc")
global_sets=("" "")
run_sets=("" "${limits[*]}")
if [ "$engine" = podman ] && command -v runc >/dev/null; then
    global_sets+=("--runtime runc" "--runtime runc")
    run_sets+=("" "${limits[*]}")
fi
engine_global=()
engine_run=()
found=no
for i in "${!global_sets[@]}"; do
    read -r -a engine_global <<<"${global_sets[$i]}"
    read -r -a engine_run <<<"${run_sets[$i]}"
    if "$engine" "${engine_global[@]}" run --rm "${engine_run[@]}" "$base" true >/dev/null 2>&1; then
        found=yes
        break
    fi
done
if [ "$found" = no ]; then
    say "$engine cannot start a container here; its error:"
    "$engine" run --rm "$base" true || true
    if [ "$if_engine" = yes ]; then
        say "skipping the image build and the demo in it: $engine does not run containers here"
        exit 0
    fi
    exit 1
fi
if [ ${#engine_global[@]} -gt 0 ] || [ ${#engine_run[@]} -gt 0 ]; then
    say "this host needs: $engine ${engine_global[*]} run ${engine_run[*]}"
fi

build_args=(-f deploy/container/Containerfile --build-arg "BASE_IMAGE=$base" -t "$image")
if [ -n "${POINTFARM_MESA:-}" ]; then build_args+=(--build-arg "POINTFARM_MESA=$POINTFARM_MESA"); fi
# The host's CA certificates reach the crate downloads as a build secret: where a proxy
# re-signs TLS, the host trusts its CA and the builder must too. Not kept in the image.
ca_bundle=${SSL_CERT_FILE:-/etc/ssl/certs/ca-certificates.crt}
if [ -s "$ca_bundle" ]; then build_args+=(--secret "id=host-ca,src=$ca_bundle"); fi
if [ -n "$binary" ]; then
    # The builder stage replaced by a folder holding out/pointfarm: the stage is skipped.
    binary_context=$(mktemp -d)
    # shellcheck disable=SC2064
    trap "rm -rf '$binary_context'" EXIT
    mkdir "$binary_context/out"
    cp "$binary" "$binary_context/out/pointfarm"
    build_args+=(--build-context "builder=$binary_context")
    say "the binary: $binary (the builder stage skipped)"
fi
if [ "$engine" = podman ]; then
    build_args+=(--ignorefile deploy/container/Containerfile.dockerignore)
else
    # The cache mounts need BuildKit (docker's default builder since 23.0).
    export DOCKER_BUILDKIT=1
fi
if [ -z "$binary" ]; then say "building $image (the builder stage compiles the release binary: minutes)"; fi
start=$SECONDS
"$engine" "${engine_global[@]}" build "${engine_run[@]}" "${build_args[@]}" . ||
    die "the image build failed"
say "built $image in $((SECONDS - start)) s ($("$engine" image inspect --format '{{.Size}}' "$image" | awk '{ printf "%.0f MB", $1 / 1e6 }'))"

if [ "$demo" = no ]; then
    exit 0
fi

out="${CARGO_TARGET_DIR:-target}/container-demo"
rm -rf "$out"
mkdir -p "$out"
out=$(cd "$out" && pwd)
say "running the demo in $image, frames to $out"
start=$SECONDS
# As the caller's user, so that the frames belong to them; the image's own user is 10001.
"$engine" "${engine_global[@]}" run --rm "${engine_run[@]}" \
    --user "$(id -u):$(id -g)" -e HOME=/tmp -v "$out:/frames:Z" \
    "$image" demo --out /frames --frames 12 --size 1280x720 ||
    die "the demo failed in the container"
frames=$(find "$out" -maxdepth 1 -name '*.png' | wc -l)
[ "$frames" -eq 12 ] || die "the demo in the container wrote $frames PNG frames, not 12 ($out)"
say "the demo in the container rendered 12 frames in $((SECONDS - start)) s: $out"
