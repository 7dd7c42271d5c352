"""The one-paragraph Markdown summaries under each result: what was asked, what came out
and how long it took."""
from __future__ import annotations

from ..compare import motion_difference
from ..controls import PRESETS, TASKS
from ..session import Result

MODE_NAMES = {"swap": "Word swap", "refine": "Refinement", "reweight": "Re-weighting", "mirror": "Mirroring"}
MIRROR_NAMES = {"lower": "the legs", "upper": "the arms", "all": "arms and legs"}
HOLD_NAMES = {"lower": "lower body (root path and legs)", "upper": "upper body (spine, arms and head)"}


def escape_md(text: str) -> str:
    return "".join("\\" + c if c in "\\`*_{}[]()#+-.!|<>~" else c for c in str(text))


def quoted(text: str) -> str:
    return f"“{escape_md(text)}”"


def _timing(result: Result, sampled: str) -> str:
    t = result.timings
    if result.reused:
        return "Same request as before: shown again without sampling."
    waited = f", waited {t['wait_s']:.1f} s" if t.get("wait_s", 0) > 0.5 else ""
    refined = f", feet refined in {t['refine_s']:.1f} s" if "refine_s" in t else ""
    return f"{sampled} in {t['sample_s']:.1f} s, rendered in {t['render_s']:.1f} s{refined}{waited}."


SAMPLER_NAMES = {"ddim": "DDIM", "dpm": "DPM-Solver++", "dpm-sde": "SDE-DPM-Solver++"}


def sampling_text(sampler: str, steps: int) -> str:
    """The sampler and its steps, as a summary names them: "50 DDIM steps", "4 consistency steps
    (distilled student)"."""
    if sampler == "consistency":
        return f"{steps} consistency step{'s' if steps != 1 else ''} (distilled student)"
    return f"{steps} {SAMPLER_NAMES.get(sampler, sampler.upper())} step{'s' if steps != 1 else ''}"


def _sampling(req, sampler: str | None = None) -> str:
    return f"seed {req.seed}, {sampling_text(sampler or 'ddim', req.steps)}, CFG {req.cfg:g}"


def warnings_block(*motions) -> str:
    """The prompt warnings (salad.models.vocabulary) of the motions, each once, as Markdown lines
    to lead a summary with; "" when there are none."""
    seen = []
    for m in motions:
        for w in getattr(m, "warnings", None) or []:
            line = f"⚠ {quoted(m.text)}: {escape_md(w)}"
            if line not in seen:
                seen.append(line)
    return "".join(f"{line}  \n" for line in seen)


def foot_refine_line(motion) -> str:
    """One short line on the planted-feet refinement (motion.info["foot_refine"]), ending in a
    Markdown line break: still to come (the preview shows the motion before it), what it did,
    or "" when it was off or the feet already stood still."""
    if getattr(motion, "pending_refinement", None) is not None:
        return "Planted feet: refined with the full video (the preview shows them before).  \n"
    report = (getattr(motion, "info", None) or {}).get("foot_refine")
    if not isinstance(report, dict) or not report.get("evaluations"):
        return ""
    before, after = report["planted_speed_mps"]
    return f"Planted feet refined: they slid at {100 * before:.0f} cm/s (rms), now {100 * after:.0f} cm/s.  \n"


def foot_lock_line(motion) -> str:
    """One short line on what the foot lock did (salad.motion.footlock's report in
    motion.info["foot_lock"]), ending in a Markdown line break; "" when it was off."""
    report = (getattr(motion, "info", None) or {}).get("foot_lock")
    if not isinstance(report, dict):
        return ""
    steps = sum((report.get("footsteps") or {}).values())
    if not steps:
        return "Foot lock: no planted footsteps to pin.  \n"
    line = (f"Foot lock: {steps} footstep{'s' if steps != 1 else ''} pinned, "
            f"feet moved at most {100 * report.get('max_shift_m', 0.0):.1f} cm")
    unreachable = report.get("unreachable_frames", 0)
    if unreachable:
        line += f", {unreachable} frame{'s' if unreachable != 1 else ''} out of reach"
    return line + ".  \n"


def summary_markdown(result: Result) -> str:
    """A generated motion."""
    r, m = result.request, result.motion
    length = "automatic length" if r.seconds is None else f"{r.seconds:g} s requested"
    return warnings_block(m) + (f"**{quoted(r.prompt)}** — {m.seconds:.1f} s ({m.frames} frames, {length}), "
            f"{_sampling(r, r.sampler)}.  \n" + foot_refine_line(m) + foot_lock_line(m) + _timing(result, "Sampled"))


def _word_changes(words_src: list[str], words_tgt: list[str], word_map: list[int]) -> tuple[list, list]:
    swapped = [(words_src[j], w) for w, j in zip(words_tgt, word_map) if j >= 0 and words_src[j] != w]
    added = [w for w, j in zip(words_tgt, word_map) if j < 0]
    return swapped, added


def edit_markdown(result: Result, word_map: list[int]) -> str:
    """An edit: the modulation(s) applied, both lengths, and where the motion changed."""
    r, src, edited = result.request, result.source, result.motion
    swapped, added = _word_changes(src.attention.words, edited.attention.words, word_map)
    what = []
    if r.mode == "swap":
        pairs = ", ".join(f"{quoted(a)} → {quoted(b)}" for a, b in swapped) or "no word changed"
        what.append(f"**Word swap** {pairs} (source maps lead for the first {r.tau:.0%} of the steps)")
    elif r.mode == "refine":
        words = ", ".join(quoted(w) for w in added) or "no word added"
        what.append(f"**Refinement** adding {words} (source maps kept from {r.tau:.0%} of the steps on)")
    for word, scale in r.reweight:
        what.append(f"**re-weighted** {quoted(word)} × {scale:g}")
    if r.mirror:
        what.append(f"**mirrored** {MIRROR_NAMES[r.mirror]} (left ↔ right)")
    held = result.params.get("hold")
    if held:
        what.append(f"{HOLD_NAMES[held]} held to the source")
    if r.self_inject > 0:
        what.append(f"source self-attention injected for the first {r.self_inject:.0%} of the steps")
    else:
        what.append("no self-attention injection")
    diff = motion_difference(src.joints, edited.joints)
    part, change = diff.most_changed
    others = sorted(diff.part_change_m.items(), key=lambda kv: -kv[1])[1:3]
    moved = (f"Most changed: **{escape_md(part)}** ({100 * change:.0f} cm on average, pelvis-relative), then "
             + ", ".join(f"{escape_md(n)} {100 * c:.0f} cm" for n, c in others)
             + f"; the pelvis path moved {100 * diff.root_change_m:.0f} cm on average.")
    line = " · ".join(what)
    k = 2 if line.startswith("**") else 0
    return (warnings_block(src, edited) + line[:k] + line[k].upper() + line[k + 1:]
            + f".  \n**{quoted(r.edited_prompt)}**: source {src.seconds:.1f} s ({src.frames} frames), edited "
            f"{edited.seconds:.1f} s ({edited.frames} frames), {_sampling(r, r.sampler)}.  \n{moved}  \n"
            + foot_refine_line(edited) + foot_lock_line(edited)
            + _timing(result, "Sampled the edited branch (the source's sampling replayed)"
                      if edited.info.get("source_replayed") else "Sampled both branches"))


def describe_control(result: Result) -> str:
    r, m = result.request, result.motion
    if r.task == "path":
        preset, frames, speed = r.detail
        return f"**Pelvis path: {PRESETS[preset]}**, {frames / m.fps:g} s at {speed:g} m/s"
    if r.task in ("mola", "targets"):
        return f"**{TASKS[r.task].split(' (')[0].capitalize()}** {quoted(r.detail[0])}"
    if r.task == "inbetween":
        frames = r.detail
        shown = ", ".join(map(str, frames[:8])) + (", …" if len(frames) > 8 else "")
        return f"**In-betweening** between {len(frames)} keyframe(s) of your last motion (frames {shown})"
    return "**Upper-body edit**: the lower body of your last motion kept"


def control_markdown(result: Result) -> str:
    """A guided motion: the task, the control error and timings."""
    r, m = result.request, result.motion
    info = m.info
    error = (f"**control error: mean {100 * info['control_mean_error_m']:.1f} cm, "
             f"max {100 * info['control_max_error_m']:.1f} cm**" if "control_mean_error_m" in info else "")
    return warnings_block(m) + (f"{describe_control(result)} · {quoted(r.prompt)} — {m.seconds:.1f} s ({m.frames} frames), "
            f"strength {r.strength:g}, {_sampling(r, r.sampler)}.  \n{error}  \n" + foot_refine_line(m)
            + foot_lock_line(m) + _timing(result, "Sampled"))
