"""Train a registration with the quality loss beside an L1 term (the README's first quick start, as a loop).

A misregistered view of an embedded scene is registered by gradient descent on a homography's
parameters, the loss L1 + lam * RegistrationQualityLoss: the warped image and its in-bounds mask
come from one differentiable warp (kornia), the mask only says where the warped image is real.
In a learned registration the parameters are a network's output; the loss goes in unchanged.

    python examples/quality_loss_training_step.py [--steps 200] [--lam 0.2]

It prints the loss as it falls and the homography's translation against the truth.
"""

from __future__ import annotations

import argparse

import kornia
import torch

from lensdist_torch import RegistrationQualityLoss, load_scene


def main(argv: list[str] | None = None) -> torch.Tensor:
    """Run the example with ``argv`` (the command line when None); returns the learned shift (2,) in px."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=200, help="gradient steps")
    parser.add_argument("--lam", type=float, default=0.2, help="weight of the quality loss beside L1")
    args = parser.parse_args(argv)

    torch.manual_seed(0)
    scene = kornia.filters.gaussian_blur2d(load_scene("gravel"), (7, 7), (1.5, 1.5))  # a smoother basin
    fixed = scene[..., 100:228, 100:228]   # (1, 1, 128, 128)
    moving = scene[..., 103:231, 98:226]   # fixed(p) = moving(p + (2, -3)): the truth
    truth = torch.tensor([2.0, -3.0])

    shift = torch.zeros(2, requires_grad=True)       # the "network": a translation, in pixels
    quality = RegistrationQualityLoss()              # smooth path, masked mean over valid blocks
    opt = torch.optim.Adam([shift], lr=0.05)
    h, w = fixed.shape[-2:]
    for step in range(args.steps):
        m = torch.eye(3).clone()
        m[:2, 2] = -shift                            # kornia samples src(M^-1 p): M moves by -shift
        warped = kornia.geometry.warp_perspective(moving, m[None], (h, w), align_corners=True)
        valid = kornia.geometry.warp_perspective(torch.ones_like(moving), m[None], (h, w), align_corners=True)
        loss = (warped - fixed).abs().mean() + args.lam * quality(warped, fixed, valid)
        opt.zero_grad()
        loss.backward()
        opt.step()
        if step % 50 == 0 or step == args.steps - 1:
            print(f"step {step:4d}  loss {float(loss.detach()):.4f}  shift {shift.detach().tolist()}")
    error = float((shift.detach() - truth).norm())
    print(
        f"learned shift {[round(v, 2) for v in shift.detach().tolist()]}, truth {truth.tolist()}, error {error:.3f} px"
    )
    return shift.detach()


if __name__ == "__main__":
    main()
