"""morphopt: find the best closed-chain mechanisms by simulating many candidate designs at once.

The design loop (linkage generator, design families, batched evaluation, CMA-ES and Optuna
studies) builds on the ``engine`` package; until it lands, ``morphopt demo`` runs the engine on
its reference mechanisms and reports what it measured.
"""

__version__ = "0.1.0"
__all__ = ["__version__"]
