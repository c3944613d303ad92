"""Experiments designed from the stage: the probe that finds each wire's working band and the thermal time
constant, and the identification excitation built on what it found."""
