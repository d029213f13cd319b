"""`SimConfig`, what `sim` runs: the station's closed loop along a scripted end-effector path (loadable from YAML:
`trivla-drake sim --config FILE --set k=v`)."""

# No `from __future__ import annotations` here: Drake's typed YAML loader reads this schema.
import dataclasses as dc
from typing import Optional

from trivla_drake.eval.setting_checks import check_port, check_record_path, check_seconds


@dc.dataclass
class SimConfig:
    """What `sim` runs."""

    # Simulated time [s].
    seconds: float = 8.0
    # Show the run live in Meshcat (localhost).
    meshcat: bool = False
    # Meshcat port (None: Drake's, 7000 up; 0: any free port).
    port: Optional[int] = None
    # Save the run as a self-contained HTML page here (None: no recording).
    record: Optional[str] = None
    # Scenarios YAML file (None: models/default.scenarios.yaml).
    scenario: Optional[str] = None
    # The scenario to load from that file.
    scenario_name: str = "default"

    def validate(self) -> None:
        """ValueError naming the flag or field of a setting that cannot run."""
        check_seconds(self.seconds, "--seconds")
        check_port(self.port, "port")
        check_record_path(self.record, "--record")
