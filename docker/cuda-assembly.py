"""Print docker/Dockerfile.cuda for docker/cuda-check.sh's assembly build, where neither nvcc nor CUDA is at hand.

Two steps change: the kernels stage copies gsplat's pure-Python wheel from docker/wheels/ instead of
compiling one, and the gsplat stage prints ``unavailable_reason()`` instead of requiring None. Every
other line stays, so the test and runtime stages are built as written. Fails if either step is not
found exactly once (the Dockerfile changed under the check).
"""

from __future__ import annotations

import re
import sys

COMPILE_STEP = re.compile(r"RUN pip install ninja setuptools wheel.*?> /wheels/torch-version\n", re.S)
COPY_STEP = (
    "RUN --mount=type=bind,source=docker/wheels,target=/src mkdir /wheels && cp /src/gsplat-*.whl /wheels && \\\n"
    '    python3 -c "import torch; print(torch.__version__)" > /wheels/torch-version\n'
)
KERNEL_CHECK = "assert why() is None, why()"


def assembly(dockerfile: str) -> str:
    """Dockerfile.cuda with the two CUDA-only steps replaced."""
    text, compiled = COMPILE_STEP.subn(lambda _: COPY_STEP, dockerfile)
    checked = text.count(KERNEL_CHECK)
    if (compiled, checked) != (1, 1):
        raise SystemExit(f"Dockerfile.cuda changed: kernels step found {compiled} times, kernel check {checked}")
    return text.replace(KERNEL_CHECK, "print(why())")


if __name__ == "__main__":
    with open(sys.argv[1], encoding="utf-8") as file:
        sys.stdout.write(assembly(file.read()))
