"""Validates deploy/kubernetes against the Kubernetes API's schemas (kubernetes-validate,
strict: an unknown field is an error) for each Kubernetes version given, and checks what
the schemas cannot: selectors that select, one daemon replica, the autoscaler's target.

    python validate.py [--kubectl KUBECTL] VERSION...

Checked: every resource file the kustomizations list, one by one; and, with kubectl, the
kustomization rendered (`kubectl kustomize`) bare and with each component and all of them,
which is what `kubectl apply -k` would send. Every YAML file under the folder must be a
kustomization, a resource or a patch one of them names, so none escapes the check.

KEDA's ScaledObject is a custom resource, outside the Kubernetes schemas: it is checked for
what KEDA needs of it here (the target Deployment exists in the same rendering, a prometheus
trigger with its server, query and threshold) and named as such. Any other kind or API
version the schemas lack (a typo such as apps/v2) is an error.
"""

import argparse
import itertools
import os
import subprocess
import sys
import tempfile

import yaml
from kubernetes_validate.utils import SchemaNotFoundError, ValidationError, validate

HERE = os.path.dirname(os.path.abspath(__file__))
CUSTOM = {("keda.sh/v1alpha1", "ScaledObject")}
WORKLOADS = {"Deployment", "StatefulSet"}


def load(path):
    with open(path) as f:
        return [doc for doc in yaml.safe_load_all(f) if doc]


def kustomization(folder):
    """The kustomization in folder: its resources and patches (paths relative to HERE)."""
    (doc,) = load(os.path.join(folder, "kustomization.yaml"))
    rel = os.path.relpath(folder, HERE)

    def path(p):
        return os.path.normpath(os.path.join(rel, p))

    resources = [path(p) for p in doc.get("resources", [])]
    patches = [path(p["path"]) for p in doc.get("patches", []) if "path" in p]
    return doc, resources, patches


def name(doc):
    return f"{doc.get('kind')}/{doc.get('metadata', {}).get('name')}"


def check_schema(doc, versions, where, errors):
    key = (doc.get("apiVersion"), doc.get("kind"))
    if key in CUSTOM:
        return "custom"
    for version in versions:
        try:
            validate(doc, version, strict=True)
        except SchemaNotFoundError as e:
            errors.append(f"{where}: {name(doc)}: {e.message}")
            return "error"
        except ValidationError as e:
            path = ".".join(str(p) for p in e.path)
            errors.append(f"{where}: {name(doc)} against Kubernetes {version}: {path}: {e.message}")
            return "error"
    return "ok"


def matches(selector, labels):
    return all(labels.get(k) == v for k, v in selector.items())


def check_semantics(docs, where, errors):
    """What the schemas cannot see, over one rendering (or one file's documents)."""
    workloads = [d for d in docs if d.get("kind") in WORKLOADS]
    pod_labels = [d["spec"]["template"]["metadata"].get("labels", {}) for d in workloads]
    for d in workloads:
        selector = d["spec"]["selector"].get("matchLabels", {})
        if not matches(selector, d["spec"]["template"]["metadata"].get("labels", {})):
            errors.append(f"{where}: {name(d)}: its selector does not match its pods' labels")
        if d["kind"] == "StatefulSet" and d["metadata"]["name"] == "pointfarm-daemon":
            if d["spec"].get("replicas") != 1:
                errors.append(f"{where}: {name(d)}: the daemon must have exactly 1 replica (sled)")
    if not workloads:
        return
    for d in docs:
        if d.get("kind") == "Service":
            selector = d["spec"].get("selector", {})
            if selector and not any(matches(selector, labels) for labels in pod_labels):
                errors.append(f"{where}: {name(d)}: selects no pods")
        if d.get("kind") == "PodDisruptionBudget":
            selector = d["spec"]["selector"].get("matchLabels", {})
            if not any(matches(selector, labels) for labels in pod_labels):
                errors.append(f"{where}: {name(d)}: selects no pods")
        if (d.get("apiVersion"), d.get("kind")) == ("keda.sh/v1alpha1", "ScaledObject"):
            check_scaled_object(d, workloads, where, errors)


def check_scaled_object(d, workloads, where, errors):
    spec = d.get("spec", {})
    target = spec.get("scaleTargetRef", {})
    kind = target.get("kind", "Deployment")
    if not any(w["kind"] == kind and w["metadata"]["name"] == target.get("name") for w in workloads):
        errors.append(f"{where}: {name(d)}: scales {kind}/{target.get('name')}, which is not there")
    if not 0 <= spec.get("minReplicaCount", 0) <= spec.get("maxReplicaCount", 100):
        errors.append(f"{where}: {name(d)}: minReplicaCount above maxReplicaCount")
    triggers = spec.get("triggers") or []
    if not triggers:
        errors.append(f"{where}: {name(d)}: no triggers")
    for t in triggers:
        meta = t.get("metadata", {})
        if t.get("type") != "prometheus":
            errors.append(f"{where}: {name(d)}: trigger {t.get('type')} is not the prometheus one")
        for key in ("serverAddress", "query", "threshold"):
            if not isinstance(meta.get(key), str) or not meta.get(key):
                errors.append(f"{where}: {name(d)}: the prometheus trigger needs {key} (a string)")


def render(kubectl, resources_rel, components_rel):
    """kubectl kustomize of an overlay of the folder with the components given."""
    with tempfile.TemporaryDirectory() as overlay:
        rel = os.path.relpath(HERE, overlay)
        doc = {"resources": [rel], "components": [f"{rel}/{c}" for c in components_rel]}
        with open(os.path.join(overlay, "kustomization.yaml"), "w") as f:
            yaml.safe_dump(doc, f)
        out = subprocess.run([kubectl, "kustomize", overlay], capture_output=True, text=True)
        if out.returncode != 0:
            raise RuntimeError(out.stderr.strip())
        return [doc for doc in yaml.safe_load_all(out.stdout) if doc]


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--kubectl", help="render the kustomizations with this kubectl")
    parser.add_argument("versions", nargs="+")
    args = parser.parse_args()

    errors = []
    _, resources, patches = kustomization(HERE)
    components = sorted(
        os.path.join("components", c)
        for c in os.listdir(os.path.join(HERE, "components"))
        if os.path.isfile(os.path.join(HERE, "components", c, "kustomization.yaml"))
    )
    kustomizations = ["kustomization.yaml"]
    for c in components:
        _, r, p = kustomization(os.path.join(HERE, c))
        resources += r
        patches += p
        kustomizations.append(os.path.join(c, "kustomization.yaml"))

    # No YAML file outside the check.
    listed = set(resources) | set(patches) | set(kustomizations)
    for folder, _, files in os.walk(HERE):
        for f in files:
            path = os.path.relpath(os.path.join(folder, f), HERE)
            if f.endswith((".yaml", ".yml")) and path not in listed:
                errors.append(f"{path}: no kustomization lists it, so it is never validated")

    counts = {"ok": 0, "custom": 0, "error": 0}
    every = []
    for path in resources:
        docs = load(os.path.join(HERE, path))
        for doc in docs:
            counts[check_schema(doc, args.versions, path, errors)] += 1
        every += docs
    check_semantics(every, "the resource files", errors)
    print(f"kubernetes: {counts['ok']} resources in {len(resources)} files valid against "
          f"Kubernetes {', '.join(args.versions)} (strict), {counts['custom']} custom "
          f"(KEDA ScaledObject: checked for its target and trigger only)")

    if args.kubectl:
        combinations = [()] + [(c,) for c in components]
        if len(components) > 1:
            combinations.append(tuple(components))
        for combination in combinations:
            label = "kustomization" + "".join(f" + {c}" for c in combination)
            try:
                docs = render(args.kubectl, resources, combination)
            except RuntimeError as e:
                errors.append(f"{label}: kubectl kustomize failed: {e}")
                continue
            result = [check_schema(doc, args.versions, label, errors) for doc in docs]
            check_semantics(docs, label, errors)
            print(f"kubernetes: {label}: {len(docs)} resources rendered, "
                  f"{result.count('ok')} valid, {result.count('custom')} custom")
    else:
        print("kubernetes: no kubectl: the kustomizations were not rendered, only their files checked")

    for e in errors:
        print(f"kubernetes: error: {e}", file=sys.stderr)
    return 1 if errors else 0


if __name__ == "__main__":
    sys.exit(main())
