"""Ax Bayesian search of loss weights (and any numeric config value), driven through ``ax.Client``."""
from .driver import SearchResult, SearchStateError, TrialRecord, load_records, run_search
from .space import Parameter, SearchConfigError, SearchSpec, parse_search_spec

__all__ = ["SearchResult", "SearchStateError", "TrialRecord", "load_records", "run_search", "Parameter",
           "SearchConfigError",
           "SearchSpec", "parse_search_spec", "run_search_from_config"]


def run_search_from_config(cfg, train_fn=None):
    """See :func:`omnidl.search.hydra_search.run_search_from_config`."""
    from .hydra_search import run_search_from_config as _run
    return _run(cfg, train_fn)
