"""Who answered and on what: simulated and human sessions are never pooled silently.

A session is *simulated* when its responder is a simulated participant (``observer``,
``random``) or its device is the simulated one (``sim://...``): its answers describe the
simulation, not people. Otherwise (``keypad`` on a real device, or ``scripted`` answers
transcribed on one) it is *human*. The responder is the sidecar's ``Responder``, else the
trials' ``responder`` column; the device is the sidecar's ``DeviceURL``.

A dataset of one kind is analysed as it is, and the report says which (a dry-run or the demo
is all simulated). A mixture is refused in one line unless the user chooses: pool them
(``include_simulated``, with a warning) or keep some responders (``responders``).
"""

from __future__ import annotations

from collections.abc import Sequence

import pandas as pd

from crs_study.analysis.load import LoadedData
from crs_study.errors import DatasetError

SIMULATED_RESPONDERS = ("observer", "random")
SIMULATED_DEVICE = "sim://"
_KEYS = ["dataset", "participant", "session"]


def session_sources(loaded: LoadedData) -> pd.DataFrame:
    """One row per session: ``dataset, participant, session, responder, device, kind``."""
    sessions = loaded.sessions.reindex(columns=[*_KEYS, "Responder", "DeviceURL"]).copy()
    from_trials = (loaded.trials.groupby(_KEYS, sort=False)["responder"]
                   .agg(lambda s: ",".join(sorted(set(s.dropna().astype(str)))))
                   .rename("trial_responder").reset_index())
    sessions[_KEYS] = sessions[_KEYS].astype(str)
    from_trials[_KEYS] = from_trials[_KEYS].astype(str)
    table = sessions.merge(from_trials, on=_KEYS, how="left")
    responder = table["Responder"].where(table["Responder"].notna(), table["trial_responder"])
    table["responder"] = responder.fillna("unknown").astype(str)
    table["device"] = table["DeviceURL"].fillna("unknown").astype(str)
    simulated = (table["responder"].str.split(":").str[0].isin(SIMULATED_RESPONDERS)
                 | table["device"].str.startswith(SIMULATED_DEVICE))
    table["kind"] = simulated.map({True: "simulated", False: "human"})
    return table[[*_KEYS, "responder", "device", "kind"]]


def summarise_sources(table: pd.DataFrame) -> list[dict]:
    """Sessions counted by kind, responder and device (the report's list)."""
    counts = table.groupby(["kind", "responder", "device"]).size().rename("sessions")
    return counts.reset_index().to_dict("records")


def select_sources(loaded: LoadedData, include_simulated: bool = False,
                   responders: Sequence[str] | None = None
                   ) -> tuple[LoadedData, pd.DataFrame, list[str]]:
    """The sessions to analyse, the source table of those kept, and notes.

    ``responders``: keep only sessions whose responder (the part before ``:``) is listed.
    Then a mixture of simulated and human sessions raises :class:`DatasetError` unless
    ``include_simulated``; all simulated is analysed with a note saying so.
    """
    table = session_sources(loaded)
    notes: list[str] = []
    if responders:
        wanted = set(responders)
        keep = table["responder"].str.split(":").str[0].isin(wanted)
        if not keep.any():
            raise DatasetError(f"no session has responder {sorted(wanted)!r}; the datasets "
                               f"hold {sorted(set(table['responder']))!r}")
        dropped = int((~keep).sum())
        if dropped:
            notes.append(f"{dropped} session(s) left out by the responder filter "
                         f"{sorted(wanted)!r}")
        table = table.loc[keep].reset_index(drop=True)
        loaded = _keep_sessions(loaded, table)
    kinds = set(table["kind"])
    if kinds == {"simulated", "human"}:
        described = "; ".join(f"{r['sessions']} {r['kind']} ({r['responder']} on {r['device']})"
                              for r in summarise_sources(table))
        if not include_simulated:
            raise DatasetError(f"simulated and human sessions together ({described}): they are "
                               "not pooled; analyse them apart, keep some with --responder "
                               "(e.g. --responder keypad), or pool them with "
                               "--include-simulated")
        notes.append(f"simulated and human sessions pooled on request ({described}): the "
                     "results mix simulated participants with people")
    elif kinds == {"simulated"}:
        notes.append("every session is simulated (responder and device in the report's "
                     "session list): the results describe the simulation, not people")
    return loaded, table, notes


def _keep_sessions(loaded: LoadedData, table: pd.DataFrame) -> LoadedData:
    keys = set(map(tuple, table[_KEYS].astype(str).to_numpy()))

    def mask(frame: pd.DataFrame) -> pd.Series:
        rows = frame[_KEYS].astype(str).apply(tuple, axis=1)
        return rows.isin(keys)

    trials = loaded.trials.loc[mask(loaded.trials)].reset_index(drop=True)
    sessions = loaded.sessions.loc[mask(loaded.sessions)].reset_index(drop=True)
    return LoadedData(trials, sessions, loaded.warnings, loaded.exclusion_counts)
