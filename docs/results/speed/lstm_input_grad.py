"""Does the LSTM's backward pay for the observation's gradient, and can a hand-written
recurrence avoid it? (BENCHMARKS.md, "Learn throughput")

    OMP_NUM_THREADS=2 python docs/results/speed/lstm_input_grad.py

Times forward + backward (median of 20) of ``nn.LSTM(699, 128)`` on a (48, 86, 699) batch,
the shipped anchor's sizes and a typical bucketed minibatch, with the input requiring a
gradient and not; then the same cell written as one input projection (``F.linear`` over all
steps: its backward needs no input gradient) plus a Python loop over the recurrence, checked
equal to ``nn.LSTM`` to 1e-5; then the input projection and the recurrence alone.
"""

import time

import torch

T, B, D, H = 48, 86, 699, 128


def median_time(fn, n: int = 20) -> float:
    times = []
    for _ in range(n):
        start = time.perf_counter()
        fn().sum().backward()
        times.append(time.perf_counter() - start)
    return sorted(times)[n // 2]


def main() -> None:
    torch.manual_seed(0)
    lstm = torch.nn.LSTM(D, H)
    x = torch.randn(T, B, D)
    x_grad = x.clone().requires_grad_(True)

    def manual() -> torch.Tensor:
        gates_x = torch.nn.functional.linear(x, lstm.weight_ih_l0, lstm.bias_ih_l0 + lstm.bias_hh_l0)
        h, c = x.new_zeros(B, H), x.new_zeros(B, H)
        outs = []
        for t in range(T):
            i, f, g, o = torch.addmm(gates_x[t], h, lstm.weight_hh_l0.t()).chunk(4, 1)
            c = torch.sigmoid(f) * c + torch.sigmoid(i) * torch.tanh(g)
            h = torch.sigmoid(o) * torch.tanh(c)
            outs.append(h)
        return torch.stack(outs)

    assert torch.allclose(manual(), lstm(x)[0], atol=1e-5)
    proj = torch.nn.Linear(D, 4 * H)
    recurrence = torch.nn.LSTM(1, H)
    x1 = torch.randn(T, B, 1)
    rows = {
        "nn.LSTM, input without gradient": lambda: lstm(x)[0],
        "nn.LSTM, input with gradient": lambda: lstm(x_grad)[0],
        "projection + Python recurrence": manual,
        "input projection alone (Linear 699 -> 512)": lambda: proj(x),
        "recurrence alone (nn.LSTM with input size 1)": lambda: recurrence(x1)[0],
    }
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, T={T} B={B} input={D} hidden={H}")
    for name, fn in rows.items():
        median_time(fn, 3)
        print(f"{name}: {1000 * median_time(fn):.1f} ms")


if __name__ == "__main__":
    main()
