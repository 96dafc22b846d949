#!/usr/bin/env bash
# Validates the Kubernetes manifests (validate.py: the Kubernetes API's schemas, strict, for
# the oldest Kubernetes the manifests are for and the newest kubernetes-validate knows), in a
# virtualenv of its own with requirements.txt's kubernetes-validate. With kubectl, the
# kustomization is rendered bare and with its components and the renderings are checked too.
set -euo pipefail
cd "$(dirname "$0")/../.."

versions=(1.29.0 1.37.0)
venv="${CARGO_TARGET_DIR:-target}/kubernetes-venv"
if [ ! -x "$venv/bin/python" ]; then
    python3 -m venv "$venv" || {
        echo "kubernetes: cannot make a Python virtualenv in $venv (apt-get install python3-venv)" >&2
        exit 1
    }
fi
"$venv/bin/python" -m pip install --quiet --disable-pip-version-check \
    -r deploy/kubernetes/requirements.txt

kubectl=()
if command -v kubectl >/dev/null; then
    kubectl=(--kubectl kubectl)
fi
"$venv/bin/python" deploy/kubernetes/validate.py "${kubectl[@]}" "${versions[@]}"
