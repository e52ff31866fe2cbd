"""Synthetic benchmark objects with known ground truth, rendered by Mitsuba 3 (`matspray synth`)."""

from matspray.synth.config import SynthConfig
from matspray.synth.make import SynthResult, make_object
from matspray.synth.shapes import SHAPES

__all__ = ["SHAPES", "SynthConfig", "SynthResult", "make_object"]
