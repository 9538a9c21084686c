"""torchrl_ftb: Flow to Better (offline preference-based RL by preferred trajectory generation).

Stages (folders): ``data`` → ``envs`` → ``datasets`` → ``preference`` → ``diffusion`` →
``flow`` → ``policy``; ``baselines`` and ``analysis`` beside them.
"""
__version__ = "0.1.0"
