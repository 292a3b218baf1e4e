"""What a fresh server process does before it serves: OpenMP policy first, then the warm-up.

Both run in a fresh interpreter: in this one, earlier tests have long loaded torch and the kernels.
"""

from __future__ import annotations

import os
import subprocess
import sys

WARM_UP_CHECK = """
import sys
from ogmapping.model import gaussians_cpu
from ogmapping.optim import blur
from ogmapping.render import cpu_kernels, cpu_projection
from ogmapping.warmup import warm_up
kernels = [cpu_kernels.bin_tiles, cpu_kernels.render_forward, cpu_kernels.render_backward, cpu_kernels.reduce_pairs,
           cpu_projection.project_forward, cpu_projection.project_backward, gaussians_cpu.assemble_forward,
           gaussians_cpu.assemble_backward, blur.blur]
assert not any(kernel.signatures for kernel in kernels)
assert 0.0 < warm_up("cpu") < 60.0
assert all(kernel.signatures for kernel in kernels), [k.__name__ for k in kernels if not k.signatures]
assert "torch._dynamo" in sys.modules  # what building the first optimiser imports
"""


def _python(code: str, environment: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-W", "error::RuntimeWarning", "-c", code], env=environment,
                          capture_output=True, text=True, timeout=300)


def test_the_server_sets_the_openmp_policy_before_torch_loads() -> None:
    """ogmapping must load before torch (ogmapping/__init__.py), or both thread pools spin."""
    environment = {key: value for key, value in os.environ.items() if key not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")}
    result = _python("import ogserver.app, os; print(os.environ['OMP_WAIT_POLICY'])", environment)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "PASSIVE"


def test_warm_up_loads_every_kernel_a_session_needs() -> None:
    result = _python(WARM_UP_CHECK)
    assert result.returncode == 0, result.stderr
