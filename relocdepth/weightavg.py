"""An exponential moving average of a network's weights (Polyak averaging).

The trainer keeps one beside the networks it trains (``TrainConfig.ema_decay``) and writes it into
every checkpoint, where localisation and evaluation take it instead of the raw weights
(:func:`relocdepth.checkpoint.load_for_inference`). Adam's last steps leave the raw weights
wherever the last batches pushed them; the average is the point they wander around.

After ``n`` updates the decay is ``min(decay, (1 + n) / (10 + n))``: the first updates follow the
weights closely, so that the average does not hold on to the initialisation for thousands of steps.
Every floating-point entry of the state dict is averaged (parameters and BatchNorm statistics); the
others (BatchNorm's step counters) are copied.
"""

from __future__ import annotations

from typing import Any


class WeightAverage:
    """``update(module)`` after each optimizer step; ``weights`` is a state dict for
    ``module.load_state_dict``."""

    def __init__(self, module: Any, decay: float) -> None:
        if not 0.0 <= decay < 1.0:
            raise ValueError(f"decay must be in [0, 1), got {decay}")
        self.decay = decay
        self.updates = 0
        self.weights = {k: v.detach().clone() for k, v in module.state_dict().items()}

    def decay_now(self) -> float:
        """The decay the next update uses."""
        n = self.updates + 1
        return min(self.decay, (1 + n) / (10 + n))

    def update(self, module: Any) -> None:
        import torch

        d = self.decay_now()
        with torch.no_grad():
            for k, v in module.state_dict().items():
                avg = self.weights[k]
                if avg.is_floating_point():
                    avg.lerp_(v.detach().to(avg.dtype), 1.0 - d)
                else:
                    avg.copy_(v)
        self.updates += 1

    def state_dict(self) -> dict[str, Any]:
        return {"decay": self.decay, "updates": self.updates, "weights": self.weights}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore a saved average (its weights and update count; the decay stays this one's)."""
        missing = self.weights.keys() - state["weights"].keys()
        if missing:
            raise ValueError(f"the saved average lacks {sorted(missing)[:3]}")
        self.weights = {k: state["weights"][k].detach().clone().to(v.device) for k, v in self.weights.items()}
        self.updates = int(state["updates"])
