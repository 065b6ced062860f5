"""Pure differentiable functions (torch/numpy only; no modules, config, I/O or global RNG)."""
