"""Strict JSON schemas of the Kubernetes API, for kubeconform, from the OpenAPI document that ships in
the `k8s.io/kubernetes` Go module (fetched from the Go module proxy, which this machine reaches).

    python deploy/kubernetes_schemas.py OUT_DIR [--version v1.31.0]

writes OUT_DIR/_definitions.json (every definition, made strict: no unknown fields) and one
`{kind}-{group}-{version}.json` per resource kind, named as kubeconform's `{{ .ResourceKind }}{{
.KindSuffix }}.json` template expects, each a reference into the shared definitions.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import urllib.request
import zipfile
from pathlib import Path

KUBERNETES_MODULE = "k8s.io/kubernetes"
DEFINITIONS_FILE = "_definitions.json"
# Types the API accepts in two JSON forms, which the OpenAPI document writes as a string only.
_TWO_FORM_TYPES = {
    "io.k8s.apimachinery.pkg.util.intstr.IntOrString": [{"type": "string"}, {"type": "integer"}],
    "io.k8s.apimachinery.pkg.api.resource.Quantity": [{"type": "string"}, {"type": "number"}],
}


def openapi_document(version: str) -> dict:
    """The Kubernetes OpenAPI v2 document of `version`, read from the module's zip on the Go proxy."""
    proxy = os.environ.get("GOPROXY", "https://proxy.golang.org").split(",")[0].split("|")[0]
    url = f"{proxy.rstrip('/')}/{KUBERNETES_MODULE}/@v/{version}.zip"
    with urllib.request.urlopen(url, timeout=120) as response:
        archive = zipfile.ZipFile(io.BytesIO(response.read()))
    return json.loads(archive.read(f"{KUBERNETES_MODULE}@{version}/api/openapi-spec/swagger.json"))


def _strict(schema):
    """`schema` with every object closed to unknown fields and refs pointing into the shared file."""
    if isinstance(schema, list):
        return [_strict(item) for item in schema]
    if not isinstance(schema, dict):
        return schema
    strict = {
        key: {name: _strict(value) for name, value in value.items()} if key == "properties" else _strict(value)
        for key, value in schema.items()
    }
    if isinstance(strict.get("$ref"), str):
        strict["$ref"] = strict["$ref"].replace("#/definitions/", f"{DEFINITIONS_FILE}#/definitions/")
    if "properties" in strict and "additionalProperties" not in strict:
        strict["additionalProperties"] = False
    return strict


def write_schemas(document: dict, out_dir: Path) -> list[str]:
    """Writes the shared definitions and one schema per kind; returns the kind files written."""
    definitions = {name: _strict(schema) for name, schema in document["definitions"].items()}
    for name, forms in _TWO_FORM_TYPES.items():
        definitions[name] = {"description": document["definitions"][name].get("description", ""), "oneOf": forms}
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / DEFINITIONS_FILE).write_text(json.dumps({"definitions": definitions}))
    written = []
    for name, schema in document["definitions"].items():
        for gvk in schema.get("x-kubernetes-group-version-kind", []):
            group = gvk["group"].split(".")[0]
            suffix = f"-{group}-{gvk['version']}" if group else f"-{gvk['version']}"
            file_name = f"{gvk['kind'].lower()}{suffix.lower()}.json"
            (out_dir / file_name).write_text(json.dumps({"$ref": f"{DEFINITIONS_FILE}#/definitions/{name}"}))
            written.append(file_name)
    return written


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out_dir", type=Path)
    parser.add_argument("--version", default="v1.31.0", help="k8s.io/kubernetes module version")
    args = parser.parse_args()
    written = write_schemas(openapi_document(args.version), args.out_dir)
    print(f"{len(written)} Kubernetes {args.version} schemas in {args.out_dir}")


if __name__ == "__main__":
    main()
