"""usmswitch.predictor: the paper's fixed-memory AR(m) predictor of a stroke's operating time.

`ARPredictor` is the online predictor (Eq. 2-6) the daemon runs per direction; `select_order` and
`aic_table` apply the AIC order selection of Eq. 8-9. Pure Python integers and floats; it imports
nothing else of ours. See docs/predictor.md.
"""

from .aic import SIGMA2_FLOOR_NS2, AicTable, min_samples
from .ar import SOUND_FIT, STATE_FORMAT, ARPredictor
from .checks import AR_MODELS, MAX_ORDER, MAX_T_NS, MODELS, check_stroke_ns
from .conditions import CONDITION_KEYS, Conditions
from .exact import ExactSolution
from .factory import DEFAULT_MODEL, Predictor, make_predictor, make_predictors
from .selection import CRITERIA, aic_table, select_order

__all__ = [
    "AR_MODELS",
    "CONDITION_KEYS",
    "CRITERIA",
    "DEFAULT_MODEL",
    "MAX_ORDER",
    "MAX_T_NS",
    "MODELS",
    "SIGMA2_FLOOR_NS2",
    "SOUND_FIT",
    "STATE_FORMAT",
    "ARPredictor",
    "AicTable",
    "Conditions",
    "ExactSolution",
    "Predictor",
    "aic_table",
    "check_stroke_ns",
    "make_predictor",
    "make_predictors",
    "min_samples",
    "select_order",
]
