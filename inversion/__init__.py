"""Inversion: signature databases, classifier, refiners and MCMC for PPR."""

# refiners and MCMC (issue 6)
from ._mcmc import (  # noqa: E402
    ChainTooShortWarning,
    MCMCConfig,
    MCMCResult,
    load_mcmc_config,
    sample_posterior,
)
from ._params import Parametrisation, PhysicalParams  # noqa: E402
from ._refine import (  # noqa: E402
    GaussianNoise,
    PhysicalBounds,
    PoissonNoise,
    RefineResult,
    SimulatorModel,
    refine,
    refine_bounded,
)
