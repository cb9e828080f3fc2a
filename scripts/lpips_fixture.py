"""Writes crates/nerf/tests/fixtures/lpips_random.json: LPIPS (AlexNet) computed by the
`lpips` package (PyTorch) with deterministic pseudo-random weights on two deterministic
images, for the Rust implementation's test (`metrics::lpips::tests`) to match.

Nothing is downloaded: the network is built with random weights (pnet_rand) and every
weight is then overwritten from a counter-based generator (splitmix64) that the Rust test
reproduces exactly, so only the expected values need committing.

    pip install torch torchvision lpips
    python scripts/lpips_fixture.py crates/nerf/tests/fixtures/lpips_random.json
"""

import json
import math
import sys

import numpy as np
import torch
import lpips

MASK = (1 << 64) - 1
CHANNELS = [(3, 64, 11), (64, 192, 5), (192, 384, 3), (384, 256, 3), (256, 256, 3)]
WIDTH, HEIGHT = 96, 80


def splitmix64(x):
    z = (x + 0x9E3779B97F4A7C15) & MASK
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & MASK
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & MASK
    return z ^ (z >> 31)


def uniform(stream, n):
    """n values in [0, 1) of stream `stream`: 24 high bits of splitmix64(stream << 32 | i)."""
    return np.array([(splitmix64((stream << 32) | i) >> 40) / float(1 << 24) for i in range(n)])


def main(out):
    model = lpips.LPIPS(net="alex", pretrained=False, pnet_rand=True, verbose=False).eval()
    # Modules keep torchvision's indices into alexnet().features: the convolutions are
    # 0, 3, 6, 8 and 10.
    slices = [model.net.slice1, model.net.slice2, model.net.slice3, model.net.slice4,
              model.net.slice5]
    convs = [s._modules[str(i)] for s, i in zip(slices, [0, 3, 6, 8, 10])]
    with torch.no_grad():
        for k, (conv, (cin, cout, ks)) in enumerate(zip(convs, CHANNELS)):
            fan_in = cin * ks * ks
            w = (2 * uniform(3 * k, cout * fan_in) - 1) * math.sqrt(6.0 / fan_in)
            b = (2 * uniform(3 * k + 1, cout) - 1) * 0.1
            h = uniform(3 * k + 2, cout) * 0.1
            conv.weight.copy_(torch.tensor(w.astype(np.float32)).reshape(cout, cin, ks, ks))
            conv.bias.copy_(torch.tensor(b.astype(np.float32)))
            model.lins[k].model[-1].weight.copy_(
                torch.tensor(h.astype(np.float32)).reshape(1, cout, 1, 1))
        n = WIDTH * HEIGHT * 3
        a = uniform(100, n).astype(np.float32)
        b = np.clip(a + 0.2 * (2 * uniform(101, n) - 1), 0, 1).astype(np.float32)
        # Packed row-major RGB in the Rust test; NCHW here.
        to_torch = lambda x: torch.tensor(x.reshape(HEIGHT, WIDTH, 3)).permute(2, 0, 1)[None]
        ta, tb = to_torch(a), to_torch(b)
        total, layers = model(ta, tb, retPerLayer=True, normalize=True)
        same = model(ta, ta, normalize=True)
    result = {
        "width": WIDTH,
        "height": HEIGHT,
        "lpips": float(total.item()),
        "per_layer": [float(l.item()) for l in layers],
        "same_image": float(same.item()),
        "made_with": f"lpips {lpips.__version__ if hasattr(lpips, '__version__') else '0.1.4'}, "
                     f"torch {torch.__version__}",
    }
    with open(out, "w") as f:
        json.dump(result, f, indent=2)
        f.write("\n")
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "lpips_random.json")
