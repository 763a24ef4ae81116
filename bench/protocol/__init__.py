"""The benchmark protocol (docs/protocol.md): what a setting is, which samples a dataset yields
under it, and what every forecast and sweep must be before it is scored.

    protocol.toml   the protocol as versioned data: settings, sample policies, ROI, minimum range
    settings.py     reads it (Protocol, Setting, SamplePolicy; active_protocol)
    samples.py      sequences -> (Sample, GroundTruth) pairs under a setting (SampleBuilder)
    validate.py     the checks on sweeps read and forecasts returned
    nosamples.py    why a split yields no samples, and the option that fixes it

The names below are what the rest of pcfbench, and plugins, import from the protocol.
"""

from pcfbench.protocol.samples import SampleBuilder, anchors, ids_hash, sample_id
from pcfbench.protocol.settings import (MIN_RANGE_M, POLICY_KINDS, PROTOCOL_FILE, ROI, SAMPLE_POLICIES, SETTINGS,
                                        Protocol, SamplePolicy, Setting, active_protocol, check_compatible,
                                        evenly_spaced, load_protocol, parse_protocol)

__all__ = [
    "MIN_RANGE_M", "POLICY_KINDS", "PROTOCOL_FILE", "ROI", "SAMPLE_POLICIES", "SETTINGS", "Protocol", "SampleBuilder",
    "SamplePolicy", "Setting", "active_protocol", "anchors", "check_compatible", "evenly_spaced", "ids_hash",
    "load_protocol", "parse_protocol", "sample_id",
]
