import pytest
import torch

# small matrices: one intra-op thread avoids contention (measured 25 ms vs 0.9 ms per Adam step on a loaded machine)
torch.set_num_threads(1)


@pytest.fixture(params=[torch.float32, torch.float64], ids=["f32", "f64"])
def dtype(request) -> torch.dtype:
    return request.param


@pytest.fixture
def count_matrix_exp(monkeypatch: pytest.MonkeyPatch) -> list[tuple[int, ...]]:
    """The shapes of every torch.matrix_exp call made during the test, in order."""
    calls: list[tuple[int, ...]] = []
    original = torch.matrix_exp

    def counting(x: torch.Tensor) -> torch.Tensor:
        calls.append(tuple(x.shape))
        return original(x)

    monkeypatch.setattr(torch, "matrix_exp", counting)
    return calls
