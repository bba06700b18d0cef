"""Helpers the tests share: the tiny catalogue (tinylayers), toy diffusers pipelines (toydiffusers), crafted PNG
bytes (pngcraft), random stacks (stackcraft), peak-memory child runs (peak) and the float64 reference compositor
(reference)."""
