"""The paper model's training step in PyTorch, for comparison with `nerf bench --model vanilla`.

Same work as our bench: 1024 rays, 64 stratified coarse samples and 128 importance samples
(the fine network sees all 192), positional encoding L=10 (position) and L=4 (direction),
8x256 trunk with the input re-joined after the 4th layer, a 256-wide feature and a 128-wide
view layer, photometric loss of both passes, Adam. float32 throughout (TF32 off unless
--tf32), as our GPU engine computes. Prints the median step time over the timed steps.

    python3 scripts/torch_paper_step.py [--rays 1024] [--steps 20] [--tf32]
"""

import argparse
import statistics
import time

import torch
from torch import nn


def encode(x, freqs):
    out = [x]
    for i in range(freqs):
        out += [torch.sin(2.0**i * x), torch.cos(2.0**i * x)]
    return torch.cat(out, -1)


class PaperMlp(nn.Module):
    def __init__(self, width=256):
        super().__init__()
        pos, view = 3 + 3 * 2 * 10, 3 + 3 * 2 * 4
        self.trunk = nn.ModuleList(
            [nn.Linear(pos, width)]
            + [nn.Linear(width + (pos if i == 4 else 0), width) for i in range(1, 8)]
        )
        self.sigma = nn.Linear(width, 1)
        self.feature = nn.Linear(width, width)
        self.view = nn.Linear(width + view, width // 2)
        self.rgb = nn.Linear(width // 2, 3)

    def forward(self, x, d):
        ex, ed = encode(x, 10), encode(d, 4)
        h = ex
        for i, layer in enumerate(self.trunk):
            if i == 4:
                h = torch.cat([h, ex], -1)
            h = torch.relu(layer(h))
        sigma = self.sigma(h)[..., 0]
        h = torch.relu(self.view(torch.cat([self.feature(h), ed], -1)))
        return torch.sigmoid(self.rgb(h)), sigma


def composite(rgb, sigma, t):
    delta = torch.cat([t[:, 1:] - t[:, :-1], torch.full_like(t[:, :1], 1e10)], -1)
    alpha = 1.0 - torch.exp(-torch.relu(sigma) * delta)
    trans = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1.0 - alpha + 1e-10], -1), -1)
    w = alpha * trans[:, :-1]
    return (w[..., None] * rgb).sum(1), w


def sample_pdf(bins, weights, n):
    pdf = (weights + 1e-5) / (weights + 1e-5).sum(-1, keepdim=True)
    cdf = torch.cat([torch.zeros_like(pdf[:, :1]), torch.cumsum(pdf, -1)], -1)
    u = torch.rand(cdf.shape[0], n, device=cdf.device)
    idx = torch.searchsorted(cdf, u, right=True).clamp(1, cdf.shape[1] - 1)
    lo, hi = torch.gather(cdf, 1, idx - 1), torch.gather(cdf, 1, idx)
    blo, bhi = torch.gather(bins, 1, idx - 1), torch.gather(bins, 1, idx)
    frac = (u - lo) / torch.where(hi - lo < 1e-5, torch.ones_like(hi), hi - lo)
    return blo + frac * (bhi - blo)


def step(coarse, fine, opt, rays, n_coarse=64, n_fine=128, near=2.0, far=6.0):
    dev = "cuda"
    o = torch.randn(rays, 3, device=dev)
    d = torch.nn.functional.normalize(torch.randn(rays, 3, device=dev), dim=-1)
    target = torch.rand(rays, 3, device=dev)
    edges = torch.linspace(near, far, n_coarse + 1, device=dev)
    t = edges[:-1] + (edges[1:] - edges[:-1]) * torch.rand(rays, n_coarse, device=dev)
    x = o[:, None] + d[:, None] * t[..., None]
    rgb, sigma = coarse(x, d[:, None].expand_as(x))
    c_coarse, w = composite(rgb, sigma, t)
    mids = 0.5 * (t[:, 1:] + t[:, :-1])
    t_fine = sample_pdf(mids, w[:, 1:-1].detach(), n_fine)
    t_all, _ = torch.sort(torch.cat([t, t_fine], -1), -1)
    x = o[:, None] + d[:, None] * t_all[..., None]
    rgb, sigma = fine(x, d[:, None].expand_as(x))
    c_fine, _ = composite(rgb, sigma, t_all)
    loss = ((c_coarse - target) ** 2).mean() + ((c_fine - target) ** 2).mean()
    opt.zero_grad(set_to_none=True)
    loss.backward()
    opt.step()
    return loss


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rays", type=int, default=1024)
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--warmup", type=int, default=5)
    ap.add_argument("--tf32", action="store_true", help="allow TF32 matrix products")
    args = ap.parse_args()
    torch.backends.cuda.matmul.allow_tf32 = args.tf32
    torch.backends.cudnn.allow_tf32 = args.tf32
    coarse, fine = PaperMlp().cuda(), PaperMlp().cuda()
    opt = torch.optim.Adam(list(coarse.parameters()) + list(fine.parameters()), lr=5e-4)
    times = []
    for i in range(args.warmup + args.steps):
        torch.cuda.synchronize()
        start = time.perf_counter()
        step(coarse, fine, opt, args.rays)
        torch.cuda.synchronize()
        if i >= args.warmup:
            times.append(time.perf_counter() - start)
    median = statistics.median(times)
    print(
        f"torch {torch.__version__} on {torch.cuda.get_device_name()}: paper step, "
        f"{args.rays} rays, tf32={'on' if args.tf32 else 'off'}: median {median * 1e3:.2f} ms "
        f"({args.rays / median:.0f} rays/s), peak memory "
        f"{torch.cuda.max_memory_allocated() / 2**20:.0f} MiB"
    )


if __name__ == "__main__":
    main()
