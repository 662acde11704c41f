"""Human operators: simulated pilots and a real person at the keyboard (DESIGN §3, §4c)."""

from dcsc_torchrl.humans.random_operator import RandomOperator

__all__ = ["RandomOperator"]
