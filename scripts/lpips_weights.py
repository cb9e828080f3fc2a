"""Writes the weights `nerf eval --lpips-weights FILE` reads: torchvision's ImageNet AlexNet
(the trunk) and the `lpips` package's linear heads (v0.1, trained on human judgements),
renamed into one safetensors file. They cannot ship with nerf (their own licences and
sizes); this makes them once, where PyTorch is installed.

    pip install torch torchvision lpips safetensors
    python scripts/lpips_weights.py lpips_alex.safetensors   # downloads AlexNet once (233 MB)
    nerf eval --run runs/lego-fast --lpips-weights lpips_alex.safetensors

Tensors: conv{1..5}.weight [out, in, k, k], conv{1..5}.bias [out], lin{1..5}.weight [out]
(all f32). With --random-trunk the trunk is left random (no download), only to check the
file format: the script then also prints the LPIPS of two test images, which
`nerf`'s loader must reproduce.
"""

import argparse

import numpy as np
import torch
import lpips
from safetensors.torch import save_file


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("out")
    parser.add_argument("--random-trunk", action="store_true")
    args = parser.parse_args()
    model = lpips.LPIPS(net="alex", pretrained=True, pnet_rand=args.random_trunk,
                        verbose=False).eval()
    slices = [model.net.slice1, model.net.slice2, model.net.slice3, model.net.slice4,
              model.net.slice5]
    # torchvision's indices into alexnet().features of the five convolutions.
    convs = [s._modules[str(i)] for s, i in zip(slices, [0, 3, 6, 8, 10])]
    tensors = {}
    for k, conv in enumerate(convs, start=1):
        tensors[f"conv{k}.weight"] = conv.weight.detach().float().contiguous()
        tensors[f"conv{k}.bias"] = conv.bias.detach().float().contiguous()
        head = model.lins[k - 1].model[-1].weight.detach().float()
        tensors[f"lin{k}.weight"] = head.reshape(-1).contiguous()
    save_file(tensors, args.out, metadata={"format": "nerf-lpips-alex-v0.1"})
    print(f"wrote {args.out}")
    if args.random_trunk:
        rng = np.random.default_rng(0)
        a = rng.random((48, 64, 3), dtype=np.float32)
        b = np.clip(a + 0.1 * rng.standard_normal((48, 64, 3), dtype=np.float32), 0, 1)
        np.save(args.out + ".a.npy", a)
        np.save(args.out + ".b.npy", b)
        t = lambda x: torch.tensor(x).permute(2, 0, 1)[None]
        with torch.no_grad():
            print("lpips", model(t(a), t(b), normalize=True).item())


if __name__ == "__main__":
    main()
