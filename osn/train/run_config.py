"""Reading a run's own ``config.yaml`` written by an older version: options added or removed since.

A run's config lists every key it trained with, so a key it lacks was added after it was written,
and a key it has that is gone was removed since. Resuming or comparing such a run must switch no
term on or off: :func:`upgrade_run_config` fills in and drops keys at the values that train the
same, and refuses, naming the key, where that cannot be.
"""

from __future__ import annotations

from typing import Any, Callable

from osn.model.fields import FIELD_ADDED_LATER, FIELD_REMOVED_OPTIONS

#: Options added after runs were first written, with the value that trained those runs (the
#: term off); :func:`upgrade_run_config` fills them in.
ADDED_LATER: dict[str, Any] = {"anchor_guide_samples": 0, "w_distortion": 0.0, "depth_robust": 0.0, "w_edge": 0.0,
                               "w_hidden_smooth": 0.0, "anchor_bias": 0.0}


def _free_space_today(d: dict[str, Any]) -> str:
    """The removed ``free_space`` choice that trains as today for config ``d``: ``ordered`` (what
    ``w_free`` carves now), or any choice where the term is off."""
    return d.get("free_space") if d.get("w_free", 1.0) == 0 else "ordered"


def _any_value(key: str) -> Callable[[dict[str, Any]], Any]:
    """For a removed option whose value changed no trained weight (what the monitor measures,
    a render shortcut below an 8-bit level, the checkpoint cadence): whatever the run held
    trained as today."""
    return lambda d: d.get(key)


#: Options a run's own ``config.yaml`` may still name though they are gone, each with the value
#: that trains as today (or a function of the whole config giving it):
#: :func:`upgrade_run_config` drops them at that value and refuses any other.
REMOVED_OPTIONS: dict[str, Any] = {"anchor_coverage": 0.9, "w_before_depth": 0.0, "before_depth_margin": 0.95, "label_erode": 0,
                                   "uncertain_acc": 0.9,  # coverage_threshold's value
                                   # sampling budgets and the scale network's size, constants now
                                   "hidden_strips": 32, "edge_rays": 64, "edge_slope": 0.02, "free_rays": 128,
                                   "scale_width": 64, "scale_layers": 4,
                                   "label_rays": 0,  # every scale step scores the whole pool
                                   # the paper's values that every config held, constants now
                                   "w_rgb": 1.0, "label_samples": 24, "coverage_threshold": 0.9, "valid_threshold": 0.95,
                                   # the field step's rejection sampling and the background colour, constants now
                                   "candidates": 4096, "background": [0.0, 0.0, 0.0],
                                   # the monitor's sample sizes: any value trained the same weights
                                   "eval_pixels": _any_value("eval_pixels"), "iou_samples": _any_value("iou_samples"),
                                   "label_trim": 0.0,  # the rounds' trim: none now
                                   # the paper's loss weights and the free-space bands, constants now
                                   "w_depth": 1.0, "w_seg": 0.01, "free_band": 4, "free_band_objects": 1,
                                   # a render shortcut below an 8-bit level: any value trained as today
                                   "skip_occluded": _any_value("skip_occluded"),
                                   # checkpoints follow eval_every now: any cadence trained the same weights
                                   "checkpoint_every": _any_value("checkpoint_every"),
                                   "free_space": _free_space_today}


#: Options that took ``auto`` (resolved by the inputs' source) and now take one number: what
#: ``auto`` trained with, for the error a run's older ``config.yaml`` gets.
AUTO_BEFORE: dict[str, str] = {"w_hidden_smooth": "0.3 on the oracle's inputs, 0 on others",
                               "final_label_trim": "0.002 on the oracle's inputs, 0.003 on others"}


def drop_removed_options(d: dict[str, Any], verb: str = "trained with") -> tuple[dict[str, Any], list[str]]:
    """Config ``d`` without the options this version no longer has, and their names: each is
    dropped where it holds the value that trains as today (:data:`REMOVED_OPTIONS`,
    ``FIELD_REMOVED_OPTIONS`` as ``field.<key>``). ``ValueError`` naming the key (``"<verb> key:
    value"``) where it holds another value: that behaviour is gone."""
    field = d.get("field") if isinstance(d.get("field"), dict) else None
    # Each removed option's value today in this config.
    today = {k: n(d) if callable(n) else n for k, n in REMOVED_OPTIONS.items()}
    today.update({f"field.{k}": v(field or {}) if callable(v) else v for k, v in FIELD_REMOVED_OPTIONS.items()})
    named = {**d, **{f"field.{k}": v for k, v in (field or {}).items()}}
    if gone := [k for k, v in named.items() if k in today and v != today[k]]:
        raise ValueError(f"{verb} " + ", ".join(f"{k}: {named[k]!r}" for k in gone) + ", which this version no "
                         "longer has (it trains as " + ", ".join(f"{k}: {today[k]!r}" for k in gone) + ")")
    out = {k: v for k, v in d.items() if k not in today}
    if field is not None:
        out["field"] = {k: v for k, v in field.items() if k not in FIELD_REMOVED_OPTIONS}
    return out, [k for k in named if k in today]


def upgrade_run_config(d: dict[str, Any]) -> dict[str, Any]:
    """A run's own ``config.yaml`` (every key it trained with) as today's options: keys added since
    take the value it trained with (:data:`ADDED_LATER`), removed ones are dropped where they held
    the value that trains as today (:func:`drop_removed_options`), so resuming or comparing an older
    run switches no term on or off. ``ValueError`` naming the key where it cannot be read so."""
    if old := [k for k in AUTO_BEFORE if d.get(k) == "auto"]:
        raise ValueError("written before " + ", ".join(old) + " became one number for every input; "
                         + "; ".join(f"its auto trained with {AUTO_BEFORE[k]}" for k in old)
                         + ": write the number into the file to resume or compare the run")
    kept, _ = drop_removed_options(d)
    out = {**ADDED_LATER, **kept}
    if isinstance(kept.get("field"), dict):
        out["field"] = {**FIELD_ADDED_LATER, **kept["field"]}
    return out
