"""`sac`: no context at all.

Trained on every training task at once, this is domain randomisation: the
reference an adaptive method must beat.
"""

from __future__ import annotations

from zeus_ros.core.methods.base import ContextMethod


class SacMethod(ContextMethod):
    """Actor and critic see phi(s) only; the latent is empty."""

    name = 'sac'
