"""Inversion: signature databases, classifier, refiners and MCMC for PPR."""

# measurement model, attitude grids, signature database, classifier, report (issue 5)
from ._classifier import (  # noqa: E402
    ATTRIBUTES,
    WEIGHT_KINDS,
    Classification,
    PreparedBank,
    attitude_error_deg,
    classify,
    design_weights,
    line_of_sight_error_deg,
    prepare,
)
from ._database import (  # noqa: E402
    BuildReport,
    CorruptChunkError,
    DatabaseSpec,
    IncompleteDatabaseError,
    TemplateBank,
    bank_in_memory,
    build_database,
    chunk_status,
    enumerate_rows,
    init_database,
    load_database,
    load_spec,
    make_signature_fn,
    spec_from_dict,
)
from ._grid import (  # noqa: E402
    AttitudeGrid,
    covering_radius,
    fibonacci_grid,
    hopf_grid,
    symmetry_group,
)
from ._noise import (  # noqa: E402
    MeasurementModel,
    NoiseModel,
    Observation,
    measure,
    measure_stokes,
    observe,
    shift_profile,
)
from ._report import evaluate  # noqa: E402
from ._synthetic import SyntheticSignatures  # noqa: E402

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
