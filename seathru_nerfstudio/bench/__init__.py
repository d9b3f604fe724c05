"""Benchmarks of SeaThru-NeRF: ``seathru-bench run`` (methods x scenes under one training
budget) and ``seathru-bench numerics`` (the renderer's quadratures against dense references)."""
