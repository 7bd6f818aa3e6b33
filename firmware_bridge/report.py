"""What the board says about itself: the summary (`edge run --json`, the replay's report) and the live
status line. Handed the parts it reads at construction; it changes none of them."""
import time



class Report:
    def __init__(self, cfg, stats, target_counts, links, readers, sync, pipeline, governor, latency, outputs, imu_slots,
                 was_lost, status):
        """stats: the tick's counters; target_counts: the target inbox's; links: the sources (the headset's first); readers: their threads;
        sync: the FrameSynchronizer; latency: firmware_bridge.latency.Latency; outputs: the PoseOutputs;
        imu_slots: the configured extra IMUs (name, slot); was_lost: each source's lost flag as the tick
        last saw it; status: where the status line goes (None: nowhere)."""
        self.cfg, self.stats, self.links, self.readers, self.sync = cfg, stats, links, readers, sync
        self.target_counts = target_counts
        self.pipeline, self.governor, self.latency, self.outputs = pipeline, governor, latency, outputs
        self.imu_slots, self.was_lost, self.status = imu_slots, was_lost, status
        self._last_log = 0.0

    def summary(self):
        """The run so far as a dict (edge run --json, the replay's report): counts, the sources' and the
        model's state, latency."""
        counts = [l.stats() for l in self.links]          # cumulative: closed sources count too
        corrupt = sum(c.get("corrupt", 0) for c in counts)
        lost = sum(c.get("missed", 0) + c.get("lost", 0) for c in counts)
        unknown = sum(c.get("unknown", 0) + c.get("dropped_old", 0) for c in counts)
        kinds = {}                  # what the dropped frames were, over every link
        for c in counts:
            for k, v in c.items():
                name = {"wrong_dlc": "framing", "bad_quaternion": "quaternion"}.get(k, k[8:] if k.startswith("corrupt_") else None)
                if name:
                    kinds[name] = kinds.get(name, 0) + v
        clock_jumps = sum(c.get("clock_jumps", 0) for c in counts) + sum(
            st.backwards + st.forwards for st in self.sync.streams.values())
        device_errors = sum(c.get("errors", 0) for c in counts)     # bus and read errors, retried
        return {**self.stats, **self.target_counts, "output_errors": self.outputs.errors, "packets_corrupt": corrupt, "packets_lost": lost, "packets_unknown": unknown,
                "packets_corrupt_by_kind": kinds, "clock_jumps": clock_jumps, "device_errors": device_errors,
                "samples_non_finite": self.sync.non_finite, "samples_unknown_tracker": self.sync.unknown_trackers,
                "ssi_switches": self.pipeline.switch_count,
                "samples": self.pipeline.samples, "samples_max": self.pipeline.max_samples,
                "samples_changes": [list(c) for c in list(self.governor.changes)[-20:]] if self.governor else [],
                "samples_change_count": self.governor.change_count if self.governor else 0,
                "lookahead_frames": self.pipeline.lookahead,
                **self.latency.summary(),
                "lag_note": "pose age: from the newest tracker sample a pose's tick used reaching the board to the "
                            "pose leaving it; motion-to-pose lag: the age plus the SSI look-ahead "
                            f"({self.pipeline.lookahead} frames, {1000.0 * self.pipeline.lookahead / self.cfg.hz:.0f} ms); "
                            f"the synchroniser's interpolation point ({1000.0 * self.cfg.sync_latency:.0f} ms back) is "
                            "inside the age, the transport to the board is not",
                "reopens": sum(l.reopens for l in self.links),
                "samples_dropped": sum(r.dropped for r in self.readers),
                "reader_threads": len(self.readers),
                "compiled_core": self.pipeline.native is not None,
                "precision": self.pipeline.precision, "precision_note": self.pipeline.precision_note,
                "int8_check": self.pipeline.manifest["int8_check"],
                "start_errors": {l.url: l.start_error for l in self.links if l.start_error},
                "imus_in_use": self.imus_in_use(), "slimevr": self.slimevr_trackers(),
                **self.target_summary(),
                "links": {l.url: {"counts": l.stats(), "reopens": l.reopens, "open": l.source is not None,
                                  **({"link": l.link_summary()} if l.link_summary() is not None else {})}
                          for l in self.links},
                **({"headset_link": self.links[0].link_summary()} if self.links[0].link_summary() is not None else {})}

    def target_summary(self):
        """The refiner's targets: how many are waiting or live, and the refused ones by reason."""
        r = self.pipeline.refiner
        reach = r.term("targets") if r is not None else None
        return {"targets_live": len(reach.targets) if reach is not None else 0,
                "targets_refused": sum(r.refused.values()) if r is not None else 0,
                "targets_refused_by_reason": dict(r.refused) if r is not None else {},
                "refine_steps": r.steps if r is not None else 0, "refined_frames": r.applied if r is not None else 0}

    def _slimevr_status(self, mac, t):
        """' | 00:01 2 sensors 98/s 80%' for one SlimeVR tracker (unused / lost when so)."""
        battery = "-" if t["battery"] is None else f"{100 * t['battery']:.0f}%"
        flags = ("" if t["in_use"] else " unused") + (" lost" if t["age_s"] > self.cfg.lost_after else "")
        return f" | {mac[-5:]} {len(t['sensors'])} sensors {t['packets_per_s']:.0f}/s {battery}{flags}"

    def slimevr_trackers(self):
        """Every SlimeVR tracker the slimevr:// sources have heard (MAC -> sensors, rate, battery, use)."""
        out = {}
        for link in self.links:
            if link.source is not None:
                out.update(link.source.trackers())
        return out

    def imus_in_use(self):
        """The extra IMUs the model reads now, with their presence flag (1 in use, fading while lost)."""
        if not self.pipeline.imus:
            return {}
        return {n: round(float(self.sync.imu_flag[k]), 2) for n, k in self.imu_slots}

    def show(self, final=False, summary=None):
        """The status line: rewritten in place on a terminal, one line every 5 s (and the last) in a log."""
        if self.status is None:
            return
        s = summary or self.summary()
        lost = [n for n, v in self.was_lost.items() if v]
        waiting = [f"{what}: waiting for {link.device}" for what, link in
                   (("headset", self.links[0]), ("pose stream", self.outputs.port)) if link is not None and link.source is None]
        line = (f"edge run | {' | '.join(waiting) + ' | ' if waiting else ''}in {s['frames_in']} out {s['frames_out']} | N={s['samples']}"
                f"{' K=' + str(s['refine_steps']) if s['targets_live'] else ''}"
                f"{'' if s['compiled_core'] else ' (numpy, no C core)'} switches {s['ssi_switches']} "
                f"| frame p99 {s['frame_ms']['p99']:.1f} ms | lag p99 {s['motion_to_pose_lag_ms_last_10s']['p99']:.0f} ms | late {s['deadline_misses']} | corrupt {s['packets_corrupt']} "
                f"| lost: {','.join(lost) or '-'}"
                + (f" | IMUs: {' '.join(n if f >= 1 else f'{n}({f:.1f})' for n, f in s['imus_in_use'].items())}"
                   if s["imus_in_use"] else "")
                + (f" | targets {s['targets_live']} live" + (f", {s['targets_refused']} refused" if s['targets_refused'] else "")
                   + (f", {s['targets_ignored']} ignored (refinement off)" if s['targets_ignored'] else "")
                   if s["targets_in"] else "")
                + "".join(self._slimevr_status(mac, t) for mac, t in s["slimevr"].items())
                + "".join(f" | {text}" for text in (link.status_text() for link in self.links)  # webxr: rate, pairing
                          if text)
                + (f" | precision {self.pipeline.precision} ({self.pipeline.precision_note})"
                   if self.pipeline.precision_note else ""))
        tty = hasattr(self.status, "isatty") and self.status.isatty()
        if tty:
            self.status.write("\r" + line + "\x1b[K" + ("\n" if final else ""))
        else:                                         # logs: one line every 5 s, and the last
            now = time.monotonic()
            if final or now - self._last_log >= 5.0:
                self._last_log = now
                self.status.write(line + "\n")
        self.status.flush()
