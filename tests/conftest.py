import pytest
import torch

# small matrices: one intra-op thread avoids contention (measured 25 ms vs 0.9 ms per Adam step on a loaded machine)
torch.set_num_threads(1)


@pytest.fixture(params=[torch.float32, torch.float64], ids=["f32", "f64"])
def dtype(request) -> torch.dtype:
    return request.param
