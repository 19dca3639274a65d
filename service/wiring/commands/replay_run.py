"""The replay's loop: the recording's blocks through the pipeline, each recorded command applied before the sample it
was applied before live, every block and its output to the outputs; the gate's checks worked out ahead in a second
process where that pays (gate_ahead.py)."""

from __future__ import annotations

from fluxcal.service.io.calfile import calibration_from_dict
from fluxcal.service.wiring.gate_ahead import GateAhead, gate_ahead_worth
from fluxcal.service.wiring.progress import Progress
from fluxcal.service.wiring.sinks import Sinks


def run_blocks(pipeline, cfg, blocks, commands: list[dict], outputs: Sinks, ahead: bool | None = None):
    """The blocks through the pipeline, each recorded command applied before the sample it was applied before live;
    every block and its output to the outputs. Returns (samples, out_seq, out_vals, replaced): the corrected
    output's seq and values, and the replay's calibrations (seq, cal_id, condition, kind). ahead: the gate's checks
    worked out in a second process (gate_ahead.py; the same results); None: where that pays."""
    total = sum(b.n_samples for b in blocks)
    if ahead is None:
        every = pipeline.check_every_chunks
        ahead = every is not None and gate_ahead_worth(total, every * pipeline.chunk)
    second = GateAhead(pipeline, lambda pl: feed(pl, cfg, blocks, commands)) if ahead else None
    progress = Progress(total, "replay")
    samples, ci = 0, 0
    out_seq, out_vals = [], []
    replaced: list[tuple[int, int, float, str]] = []
    try:
        for block in blocks:
            ci = commands_before(pipeline, cfg, block, commands, ci, outputs, replaced)
            result = pipeline.process(block)
            replaced += [(ev.seq, int(ev.detail["cal_id"]), float(ev.detail.get("condition", "nan")), ev.kind)
                         for ev in result.events if ev.kind == "calibration"]
            samples += block.n_samples
            outputs.raw(block)
            if result.corrected is not None:
                outputs.corrected(result.corrected)
                out_seq.append(result.corrected.seq)
                out_vals.append(result.corrected.corrected_nT)
            outputs.flush()                   # the end of the block's turn, as the service's loop ends it
            progress.to(samples)
    finally:
        progress.close()
        if second is not None:
            second.close()
    return samples, out_seq, out_vals, replaced


def feed(pipeline, cfg, blocks, commands: list[dict]) -> None:
    """The blocks and commands of run_blocks through a pipeline, without outputs (gate_ahead's second process)."""
    ci = 0
    for block in blocks:
        ci = commands_before(pipeline, cfg, block, commands, ci, None, [])
        pipeline.process(block)


def commands_before(pipeline, cfg, block, commands: list[dict], ci: int, outputs: Sinks | None,
                     replaced: list) -> int:
    """The recorded commands from commands[ci] on that were applied before the block's first sample, applied
    (and told to the outputs); returns the index of the next."""
    while ci < len(commands) and block.n_samples and commands[ci]["seq"] <= int(block.seq[0]):
        c = commands[ci]
        payload = (calibration_from_dict(c["calibration"]) if c.get("name") == "apply"
                   else c.get("effect"))
        ev = pipeline.command(c["name"], payload, seq=c["seq"], t_s=float("nan"))
        if c.get("name") == "apply" and "note" not in c:
            pipeline.held = False     # recorded before applied calibrations were held: as that live run
        if c.get("name") == "add-effect":   # refitted over the window: conditioned at most as the gate allows
            replaced.append((int(c["seq"]), int(ev.detail["cal_id"]), float(cfg.estimator.gate_condition),
                             "add-effect"))
        if outputs is not None:
            outputs.command(c)
        ci += 1
    return ci
