"""The studio's model thread: one thread runs every model call, and it alone runs torch on more
than one core while a studio is up."""
from __future__ import annotations

import os
import re
import subprocess
import sys
import threading

import pytest
import torch

from app.model_thread import ModelThread


def test_calls_run_on_one_thread_with_their_values_and_errors():
    mt = ModelThread()
    try:
        names = {mt.run(lambda: threading.current_thread().name) for _ in range(3)}
        assert len(names) == 1 and names != {threading.current_thread().name}
        assert mt.run(lambda a, b=0: a + b, 2, b=3) == 5
        with pytest.raises(ValueError, match="bad"):
            mt.run(lambda: (_ for _ in ()).throw(ValueError("bad")))
        # a model call that makes another one (refinement inside a request) runs it in place
        assert mt.run(lambda: mt.run(lambda: threading.current_thread().name)) in names
    finally:
        mt.close()


def test_only_the_model_thread_keeps_several_torch_threads_and_the_count_comes_back():
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    first, second = ModelThread(), ModelThread()
    try:
        first.own_torch()
        second.own_torch()
        assert torch.get_num_threads() == 1
        assert first.run(torch.get_num_threads) == 2 and second.run(torch.get_num_threads) == 2
        counts = []
        other = threading.Thread(target=lambda: counts.append(torch.get_num_threads()))
        other.start()
        other.join()
        assert counts == [1]
        first.close()
        assert torch.get_num_threads() == 1          # the second studio still owns it
    finally:
        first.close()
        second.close()
    assert torch.get_num_threads() == 2
    torch.set_num_threads(before)


def _gomp_spincount(code: str, **env) -> str:
    """GOMP_SPINCOUNT as torch's OpenMP runtime took it in a fresh interpreter running `code` (libgomp prints its
    settings at load with OMP_DISPLAY_ENV); skips where torch runs another OpenMP runtime."""
    environ = {k: v for k, v in os.environ.items() if k != "GOMP_SPINCOUNT"} | {"OMP_DISPLAY_ENV": "VERBOSE"} | env
    out = subprocess.run([sys.executable, "-c", code + "; import torch; torch.ones(8).sum()"], env=environ,
                         capture_output=True, text=True, timeout=120, check=True)
    found = re.search(r"GOMP_SPINCOUNT = '(\d+)'", out.stdout + out.stderr)
    if found is None:
        pytest.skip("torch does not run on libgomp here")
    return found.group(1)


def test_importing_salad_or_the_studio_first_shortens_openmp_spinning_unless_the_caller_chose():
    assert _gomp_spincount("pass") != "1000"             # libgomp's own default (300000 in torch 2.13's), for comparison
    assert _gomp_spincount("import salad") == "1000"
    assert _gomp_spincount("import app") == "1000"
    assert _gomp_spincount("import salad", GOMP_SPINCOUNT="5000") == "5000"
