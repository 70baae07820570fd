SHELL := bash
.SHELLFLAGS := -eu -o pipefail -c
.DELETE_ON_ERROR:
MAKEFLAGS += --warn-undefined-variables --no-builtin-rules

PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
PROTOS := $(wildcard proto/fractoscope/v1/*.proto)
# The three distributions, installed editable: the client (whose build generates the stubs from
# proto/ into clients/python/fractoscope/v1), the services, and the CLI with its 'local' extra.
DISTRIBUTIONS := clients/python/pyproject.toml clients/python/setup.py services/pyproject.toml clients/cli/pyproject.toml
STAMP := $(VENV)/.installed
NODE_STAMP := node_modules/.installed
WEB := clients/web
WEB_STAMP := $(WEB)/node_modules/.installed
# Where an installed server finds the web viewer: sys.prefix/share/fractoscope/web (http.server).
WEB_LINK := $(VENV)/share/fractoscope/web
DATA ?= ./data
PORT ?= 8080
GRPC_PORT ?= 50051
CHROMIUM := /usr/bin/chromium
WRK := /usr/bin/wrk
PDFTOPPM := /usr/bin/pdftoppm
CURL := /usr/bin/curl
GHZ := .tools/bin/ghz
# Go tools for validating the Kubernetes manifests, built from the Go module proxy, and the
# Kubernetes API's JSON schemas for them (deploy/kubernetes_schemas.py).
TOOLS := .tools
KUBECONFORM := $(TOOLS)/bin/kubeconform
KUSTOMIZE := $(TOOLS)/bin/kustomize
KUBE_SCHEMAS := $(TOOLS)/kubernetes-schemas/.written
# SeaweedFS, the S3 server of the store tests (tests/s3_server.py): its replace directives rule out
# `go install`, so it is built inside its downloaded module.
WEED := $(TOOLS)/bin/weed
SEAWEEDFS := github.com/seaweedfs/seaweedfs@v0.0.0-20261109003541-7506e5f91cd6

.PHONY: install proto run test check bench load lint clean

## install: create .venv with the three distributions and the development tools, the stubs, the JS packages
install: $(STAMP) $(NODE_STAMP) $(WEB_STAMP) $(WEB_LINK)

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip

# setuptools warns of every editable install, in a banner of a dozen lines each (the folders of
# one name it warns of are these distributions' own): that one warning is filtered, no other.
$(STAMP): pyproject.toml $(DISTRIBUTIONS) $(PROTOS) | $(BIN)/python
	PYTHONWARNINGS="ignore:Editable installation" $(BIN)/pip install --quiet -e clients/python -e services -e 'clients/cli[local]' --group dev
	touch $@

## proto: regenerate the gRPC stubs (the client's build does it from proto/)
proto: $(STAMP)

# The Khronos glTF validator and playwright-core, with which the tests check our GLBs and drive
# Chromium; the web viewer's own package (three.js, 3DTilesRendererJS) in clients/web.
$(NODE_STAMP): package.json package-lock.json
	npm ci --no-audit --no-fund --loglevel=error
	touch $@

$(WEB_STAMP): $(WEB)/package.json $(WEB)/package-lock.json
	npm ci --prefix $(WEB) --no-audit --no-fund --loglevel=error
	touch $@

$(WEB_LINK): | $(BIN)/python
	mkdir -p $(dir $@)
	ln -sfn $(abspath $(WEB)) $@

## run: the main job on embedded defaults: services and viewer on loopback until Ctrl-C
run: install
	$(BIN)/fracto demo --data $(DATA) --http-port $(PORT) --port $(GRPC_PORT)

# Debian's Chromium for the browser test (never a browser downloaded by a test tool), wrk, the
# HTTP load generator of `make load` and `make bench`, and curl, with which the probe suite sends
# gRPC calls of any bytes (tests/hostile).
$(CHROMIUM) $(WRK) $(CURL):
	if [ "$$(id -u)" = 0 ]; then SUDO=; else SUDO=sudo; fi; \
	$$SUDO apt-get update -qq && $$SUDO apt-get install -y -qq --no-install-recommends $(notdir $@) >/dev/null

# Poppler's pdftoppm (and pdftotext), with which the tests open the measurement report's PDF.
$(PDFTOPPM):
	if [ "$$(id -u)" = 0 ]; then SUDO=; else SUDO=sudo; fi; \
	$$SUDO apt-get update -qq && $$SUDO apt-get install -y -qq --no-install-recommends poppler-utils >/dev/null

$(KUBECONFORM):
	GOBIN=$(abspath $(TOOLS)/bin) go install github.com/yannh/kubeconform/cmd/kubeconform@v0.6.7

$(GHZ):
	GOBIN=$(abspath $(TOOLS)/bin) go install github.com/bojand/ghz/cmd/ghz@v0.120.0

$(KUSTOMIZE):
	GOBIN=$(abspath $(TOOLS)/bin) go install sigs.k8s.io/kustomize/kustomize/v5@v5.5.0

$(WEED):
	dir=$$(go mod download -json $(SEAWEEDFS) | $(PYTHON) -c 'import json, sys; print(json.load(sys.stdin)["Dir"])'); \
	cd "$$dir" && go build -o $(abspath $@) ./weed

$(KUBE_SCHEMAS): deploy/kubernetes_schemas.py
	$(PYTHON) deploy/kubernetes_schemas.py $(dir $@) --version v1.31.0
	touch $@

## test: the whole test suite
test: install $(CHROMIUM) $(PDFTOPPM) $(CURL) $(KUBECONFORM) $(KUSTOMIZE) $(KUBE_SCHEMAS) $(WEED)
	$(MAKE) --no-print-directory lint
	$(BIN)/python -m pytest -q

## check: the quick loop, before each commit: lint, the contracts, the type check and, on two workers, the tests that start no server or browser (neither slow nor server); tests whose tools are missing skip
check: install
	$(MAKE) --no-print-directory lint
	$(BIN)/python -m pytest -q -n 2 --dist loadfile -m "not slow and not server"

## bench: speed, memory and accuracy figures, written to bench-results/
bench: install $(WRK) $(GHZ)
	$(BIN)/python -m benchmarks.matching --out bench-results
	$(BIN)/python -m benchmarks.profile --out bench-results
	$(BIN)/python -m benchmarks.star --out bench-results
	$(BIN)/python -m benchmarks.accuracy --out bench-results
	$(BIN)/python -m benchmarks.renderers --out bench-results
	$(BIN)/python -m benchmarks.sigma_calibration --out bench-results
	$(BIN)/python -m benchmarks.views --out bench-results
	$(BIN)/python -m benchmarks.relief_sign --out bench-results
	$(BIN)/python -m benchmarks.occlusion --out bench-results --seeds 2
	$(BIN)/python -m benchmarks.meshing --out bench-results
	$(BIN)/python -m benchmarks.exports --out bench-results
	$(BIN)/python -m benchmarks.surface_analysis --out bench-results
	$(BIN)/python -m benchmarks.serving --out bench-results
	$(BIN)/python -m benchmarks.replicas --out bench-results
	$(BIN)/python -m benchmarks.scale_out --out bench-results --one-cpu-per-replica --peers 1 2
	$(BIN)/python -m benchmarks.page_faults --out bench-results

## load: tiles over HTTP (wrk) and tiles, zooms and profiles over gRPC (ghz) at concurrency 50 for 60 s each, into bench-results/load.json; then one tile replica against two (bench-results/replicas.json); then the hostile probe's long cases (tests/hostile, pytest --load) and its figures (bench-results/hostile.json)
load: install $(WRK) $(GHZ) $(CURL) $(WEED)
	$(BIN)/python -m benchmarks.serving --out bench-results --name load --concurrency 50 --duration-s 60
	$(BIN)/python -m benchmarks.replicas --out bench-results --concurrency 50 --duration-s 60
	$(BIN)/python -m pytest -q --load -m load tests/hostile
	$(BIN)/python -m benchmarks.hostile --out bench-results

## lint: formatting, lint rules, the import layering and the type check (mypy, no error outside mypy-baseline.txt)
lint: install
	$(BIN)/ruff format --check
	$(BIN)/ruff check
	$(BIN)/lint-imports
	found=$$($(BIN)/mypy) || [ $$? -eq 1 ]; $(BIN)/mypy-baseline filter <<< "$$found"

clean:
	rm -rf $(VENV) clients/python/fractoscope/v1 build node_modules $(WEB)/node_modules $(TOOLS) .mypy_cache
	find . -name '*.egg-info' -prune -exec rm -rf {} +
