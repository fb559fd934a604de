"""The flight review page: one self-contained HTML file per flight, in the spirit of PX4's Flight Review.

`uavsearch replay RUN_DIR --html` (or `replay FILE.tlog --html`) writes it. It holds:

- the track in 3D and from above, with the view points and the search area;
- altitude, velocity, attitude and estimator error on one shared, zoomable time axis (simulation time,
  the vehicle's time_boot), with the flight modes as coloured bands and every STATUSTEXT as an event;
- for a run directory, per view: the camera frame with the grid projected at the reported pose, this
  view's per-cell p(occupied), the fused map with the ground truth, and Aacc / F1 so far (a slider).

Plotly draws it: it writes standalone HTML with plotly.js inlined (no server, no network, opens from a
file in any browser), gives linked zoom on shared axes, hover read-outs and sliders without custom
JavaScript, and is a maintained, widely used library; matplotlib's PNGs (the plain replay) cannot zoom.

Truth: the telemetry log holds what the vehicle reported (its estimate). The true pose is known at each
view (the simulated camera logs it), so the estimator error is plotted there; between views the plot
shows the estimate against the raw GPS fix, and against SIM_STATE when a log has it.
"""

from __future__ import annotations

import base64
import html
import math
import sys
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import LogError
from ..flight.commander import PX4_MODES
from ..flight.mavlink.wire_units import CM_S, DEG_E7, home_lla, lla, seconds
from ..geometry import GeodeticOrigin

_MODE_COLOURS = {"TAKEOFF": "#fdd49e", "HOLD": "#c6dbef", "MISSION": "#c7e9c0", "RTL": "#fcbba1",
                 "LAND": "#dadaeb", "OFFBOARD": "#fee391", "POSCTL": "#d9f0d3"}
_SEVERITY = ["EMERGENCY", "ALERT", "CRITICAL", "ERROR", "WARNING", "NOTICE", "INFO", "DEBUG"]


def mode_name(custom_mode: int) -> str:
    """A HEARTBEAT's PX4 custom_mode as the autopilot names it (its own table), else 'main/sub'."""
    main, sub = (custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF
    for name, ms in PX4_MODES.items():
        if ms == (main, sub):
            return name
    return f"{main}/{sub}"


@dataclass
class Telemetry:
    """Time series of one vehicle from a telemetry log; times are the vehicle's time since boot (s)."""

    pos: dict = field(default_factory=lambda: {k: [] for k in ("t", "lat", "lon", "alt", "vn", "ve", "vd")})
    att: dict = field(default_factory=lambda: {k: [] for k in ("t", "roll", "pitch", "yaw")})
    gps: dict = field(default_factory=lambda: {k: [] for k in ("t", "lat", "lon", "alt")})
    truth: dict = field(default_factory=lambda: {k: [] for k in ("t", "lat", "lon", "alt")})
    modes: list = field(default_factory=list)  # [(t, name, armed)] at each change
    events: list = field(default_factory=list)  # [(t, severity name, text)]
    captures: list = field(default_factory=list)  # [(t, lat, lon, alt, index)]
    home: tuple | None = None
    messages: int = 0


def read_telemetry(path, system_id: int | None = None) -> Telemetry:
    """The vehicle's (`system_id`, default the first autopilot that heartbeats) position, attitude, GPS, modes
    and events."""
    from pymavlink import mavutil

    path = Path(path)
    if not path.is_file():
        raise LogError(f"cannot read {path}: no such file")
    try:
        conn = mavutil.mavlink_connection(str(path), dialect="common", robust_parsing=True)
    except Exception as e:  # noqa: BLE001 - an unreadable file is one line
        raise LogError(f"cannot read {path}: {e}") from None
    tel = Telemetry()
    sysid, t_ms, last_mode = system_id, 0, None
    seen_caps = set()
    M = mavutil.mavlink
    try:
        while True:
            m = conn.recv_match()
            if m is None:
                break
            typ = m.get_type()
            if typ == "BAD_DATA":
                continue
            tel.messages += 1
            src, comp = m.get_srcSystem(), m.get_srcComponent()
            if typ == "HEARTBEAT" and sysid is None and m.autopilot != M.MAV_AUTOPILOT_INVALID \
                    and m.type != M.MAV_TYPE_GCS:
                sysid = src
            if sysid is None or src != sysid:
                continue
            if hasattr(m, "time_boot_ms"):
                t_ms = max(t_ms, int(m.time_boot_ms))
            t = seconds(t_ms)
            if typ == "GLOBAL_POSITION_INT" and comp == 1:
                for k, v in zip(("t", "lat", "lon", "alt", "vn", "ve", "vd"),
                                (t, *lla(m), m.vx * CM_S, m.vy * CM_S, m.vz * CM_S)):
                    tel.pos[k].append(v)
            elif typ == "ATTITUDE" and comp == 1:
                for k, v in zip(("t", "roll", "pitch", "yaw"), (t, m.roll, m.pitch, m.yaw)):
                    tel.att[k].append(math.degrees(v) if k != "t" else v)
            elif typ == "GPS_RAW_INT" and comp == 1 and m.fix_type >= 3:
                tg = m.time_usec * 1e-6 if 0 < m.time_usec < 1e12 else t  # time since boot, as PX4 sends it
                for k, v in zip(("t", "lat", "lon", "alt"), (tg, *lla(m))):
                    tel.gps[k].append(v)
            elif typ == "SIM_STATE":
                for k, v in zip(("t", "lat", "lon", "alt"), (t, m.lat_int * DEG_E7 if m.lat_int else m.lat,
                                                             m.lon_int * DEG_E7 if m.lon_int else m.lon, m.alt)):
                    tel.truth[k].append(v)
            elif typ == "HEARTBEAT" and comp == 1:
                mode = (mode_name(m.custom_mode), bool(m.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED))
                if mode != last_mode:
                    tel.modes.append((t, *mode))
                    last_mode = mode
            elif typ == "STATUSTEXT":
                sev = _SEVERITY[m.severity] if 0 <= m.severity < len(_SEVERITY) else str(m.severity)
                tel.events.append((t, sev, str(m.text).rstrip("\x00")))
            elif typ == "CAMERA_IMAGE_CAPTURED" and m.capture_result == 1 and m.image_index not in seen_caps:
                seen_caps.add(m.image_index)
                tel.captures.append((t, *lla(m), int(m.image_index)))
            elif typ == "HOME_POSITION" and tel.home is None:
                tel.home = home_lla(m)
    finally:
        conn.close()
    if sysid is None:
        raise LogError(f"{path}: no autopilot HEARTBEAT (not a vehicle's telemetry log)")
    return tel


# --------------------------------------------------------------------------------------------------
# figures


def _origin(tel: Telemetry, home: dict | None) -> GeodeticOrigin:
    if home:
        return GeodeticOrigin(float(home["lat_deg"]), float(home["lon_deg"]), float(home["alt_m"]))
    if tel.home:
        return GeodeticOrigin(*tel.home)
    if tel.pos["t"]:
        return GeodeticOrigin(tel.pos["lat"][0], tel.pos["lon"][0], tel.pos["alt"][0])
    return GeodeticOrigin()


def _enu(origin: GeodeticOrigin, lat, lon, alt) -> np.ndarray:
    if not len(lat):
        return np.zeros((0, 3))
    return np.atleast_2d(origin.geodetic_to_enu(np.column_stack([lat, lon, alt])))


def _mode_bands(tel: Telemetry, t_end: float):
    """[(t0, t1, name, armed)] from the mode changes."""
    out = []
    for i, (t, name, armed) in enumerate(tel.modes):
        t1 = tel.modes[i + 1][0] if i + 1 < len(tel.modes) else t_end
        if t1 > t:
            out.append((t, t1, name, armed))
    return out


def track_figure(tel: Telemetry, origin: GeodeticOrigin, views_enu=None, area_m: float | None = None,
                 team: dict | None = None):
    """`team` ({system id: Telemetry} of the other vehicles of a team): their tracks too, one colour each."""
    import plotly.graph_objects as go
    from plotly.subplots import make_subplots

    p = _enu(origin, tel.pos["lat"], tel.pos["lon"], tel.pos["alt"])
    t = np.asarray(tel.pos["t"])
    fig = make_subplots(rows=1, cols=2, specs=[[{"type": "scene"}, {"type": "xy"}]], column_widths=[0.55, 0.45],
                        subplot_titles=("track (3D, ENU m from home)", "track from above"))
    line = dict(color=t, colorscale="Viridis", width=4, colorbar=dict(title="t [s]", x=0.5, len=0.8))
    fig.add_trace(go.Scatter3d(x=p[:, 0], y=p[:, 1], z=p[:, 2], mode="lines", line=line, name="track",
                               hovertemplate="t %{customdata:.1f} s<br>E %{x:.1f} N %{y:.1f} U %{z:.1f}<extra></extra>",
                               customdata=t), 1, 1)
    fig.add_trace(go.Scatter(x=p[:, 0], y=p[:, 1], mode="lines", line=dict(color="#444", width=2), name="track (top)",
                             customdata=t, hovertemplate="t %{customdata:.1f} s<br>E %{x:.1f} N %{y:.1f}<extra></extra>"),
                  1, 2)
    for sid, other in (team or {}).items():
        q = _enu(origin, other.pos["lat"], other.pos["lon"], other.pos["alt"])
        colour = ("#d62728", "#2ca02c", "#9467bd", "#8c564b", "#e377c2")[(sid - 2) % 5]
        fig.add_trace(go.Scatter3d(x=q[:, 0], y=q[:, 1], z=q[:, 2], mode="lines", line=dict(color=colour, width=4),
                                   name=f"vehicle {sid}"), 1, 1)
        fig.add_trace(go.Scatter(x=q[:, 0], y=q[:, 1], mode="lines", line=dict(color=colour, width=2),
                                 name=f"vehicle {sid} (top)"), 1, 2)
        p = np.vstack([p, q])
    if views_enu is not None and len(views_enu):
        v = np.asarray(views_enu, float)
        labels = [str(i + 1) for i in range(len(v))]
        fig.add_trace(go.Scatter3d(x=v[:, 0], y=v[:, 1], z=v[:, 2], mode="markers+text", text=labels,
                                   marker=dict(size=5, color="crimson"), name="views"), 1, 1)
        fig.add_trace(go.Scatter(x=v[:, 0], y=v[:, 1], mode="markers+text", text=labels, textposition="top right",
                                 marker=dict(size=10, color="crimson", symbol="square"), name="views (top)"), 1, 2)
    if area_m:
        h = area_m / 2
        fig.add_trace(go.Scatter(x=[-h, h, h, -h, -h], y=[-h, -h, h, h, -h], mode="lines",
                                 line=dict(color="royalblue", dash="dot"), name="search area"), 1, 2)
    fig.update_xaxes(title_text="E [m]", row=1, col=2)
    fig.update_yaxes(title_text="N [m]", scaleanchor="x", scaleratio=1, row=1, col=2)
    # true proportions: the same metres on E and N, the search area (or the track) in view
    pts = np.vstack([p[:, :2], np.zeros((1, 2))] + ([np.asarray(views_enu)[:, :2]] if views_enu is not None
                                                    and len(views_enu) else []))
    h = max((area_m or 0.0) / 2, float(np.abs(pts).max()) + 5.0)
    top = max(float(p[:, 2].max()) if len(p) else 1.0, 1.0)
    fig.update_layout(height=520, margin=dict(l=10, r=10, t=40, b=10), legend=dict(orientation="h"),
                      scene=dict(aspectmode="manual",
                                 aspectratio=dict(x=1, y=1, z=float(np.clip(top / (2 * h), 0.4, 1.5))),
                                 xaxis=dict(title="E", range=[-h, h]), yaxis=dict(title="N", range=[-h, h]),
                                 zaxis=dict(title="U", range=[0, top * 1.05])))
    return fig


def timeseries_figure(tel: Telemetry, origin: GeodeticOrigin, view_truth=None):
    """Altitude, velocity, attitude, estimator error and events on one shared time axis.

    view_truth: [(t, estimated ENU, true ENU)] at each view (run directories)."""
    import plotly.graph_objects as go
    from plotly.subplots import make_subplots

    rows = ["altitude above home [m]", "velocity [m/s]", "attitude [deg]", "estimator error [m]", "events"]
    fig = make_subplots(rows=5, cols=1, shared_xaxes=True, vertical_spacing=0.03, subplot_titles=rows,
                        row_heights=[0.24, 0.22, 0.22, 0.2, 0.12])
    t = np.asarray(tel.pos["t"])
    p = _enu(origin, tel.pos["lat"], tel.pos["lon"], tel.pos["alt"])
    g = _enu(origin, tel.gps["lat"], tel.gps["lon"], tel.gps["alt"])
    fig.add_trace(go.Scatter(x=t, y=p[:, 2], name="altitude (estimate)", line=dict(color="#1f77b4")), 1, 1)
    if len(g):
        fig.add_trace(go.Scatter(x=tel.gps["t"], y=g[:, 2], name="altitude (GPS)", mode="lines",
                                 line=dict(color="#aaa", width=1)), 1, 1)
    for key, colour in (("vn", "#d62728"), ("ve", "#2ca02c"), ("vd", "#1f77b4")):
        fig.add_trace(go.Scatter(x=t, y=tel.pos[key], name=f"{key[1].upper()} velocity", line=dict(color=colour)), 2, 1)
    if len(t):
        speed = np.hypot(tel.pos["vn"], tel.pos["ve"])
        fig.add_trace(go.Scatter(x=t, y=speed, name="ground speed", line=dict(color="#555", dash="dot")), 2, 1)
    for key, colour in (("roll", "#d62728"), ("pitch", "#2ca02c"), ("yaw", "#1f77b4")):
        fig.add_trace(go.Scatter(x=tel.att["t"], y=tel.att[key], name=key, line=dict(color=colour)), 3, 1)
    # estimator error: against the truth where it is known, against the GPS fix in between
    if len(g) and len(t):
        est_at_gps = np.column_stack([np.interp(tel.gps["t"], t, p[:, k]) for k in range(3)])
        d = est_at_gps - g
        fig.add_trace(go.Scatter(x=tel.gps["t"], y=np.hypot(d[:, 0], d[:, 1]), name="horizontal, estimate - GPS",
                                 line=dict(color="#bbb", width=1)), 4, 1)
    if tel.truth["t"]:
        tr = _enu(origin, tel.truth["lat"], tel.truth["lon"], tel.truth["alt"])
        est = np.column_stack([np.interp(tel.truth["t"], t, p[:, k]) for k in range(3)])
        d = est - tr
        fig.add_trace(go.Scatter(x=tel.truth["t"], y=np.hypot(d[:, 0], d[:, 1]), name="horizontal, estimate - truth",
                                 line=dict(color="#9467bd")), 4, 1)
        fig.add_trace(go.Scatter(x=tel.truth["t"], y=np.abs(d[:, 2]), name="vertical, estimate - truth",
                                 line=dict(color="#8c564b")), 4, 1)
    if view_truth:
        vt = np.array([v[0] for v in view_truth])
        d = np.array([np.subtract(v[1], v[2]) for v in view_truth])
        fig.add_trace(go.Scatter(x=vt, y=np.hypot(d[:, 0], d[:, 1]), name="horizontal, estimate - truth (views)",
                                 mode="markers+lines", marker=dict(size=9, color="#9467bd")), 4, 1)
        fig.add_trace(go.Scatter(x=vt, y=np.abs(d[:, 2]), name="vertical, estimate - truth (views)",
                                 mode="markers+lines", marker=dict(size=9, color="#8c564b", symbol="diamond")), 4, 1)
        true_alt = np.array([v[2][2] for v in view_truth])
        fig.add_trace(go.Scatter(x=vt, y=true_alt, name="altitude (truth, views)", mode="markers",
                                 marker=dict(size=9, color="black", symbol="x")), 1, 1)
    # events: STATUSTEXT and views as markers on their own row
    if tel.events:
        fig.add_trace(go.Scatter(x=[e[0] for e in tel.events], y=[1.0] * len(tel.events), mode="markers",
                                 name="STATUSTEXT", marker=dict(size=11, color="#ff7f0e", symbol="triangle-down"),
                                 text=[f"{e[1]}: {html.escape(e[2])}" for e in tel.events],
                                 hovertemplate="t %{x:.1f} s<br>%{text}<extra></extra>"), 5, 1)
    if tel.captures:
        fig.add_trace(go.Scatter(x=[c[0] for c in tel.captures], y=[0.0] * len(tel.captures), mode="markers+text",
                                 name="photos", text=[f"view {i + 1}" for i in range(len(tel.captures))],
                                 textposition="top center", marker=dict(size=10, color="crimson", symbol="square")),
                      5, 1)
    t_end = max([t[-1] if len(t) else 0.0] + [e[0] for e in tel.events])
    for t0, t1, name, armed in _mode_bands(tel, t_end):
        colour = _MODE_COLOURS.get(name, "#eeeeee")
        fig.add_vrect(x0=t0, x1=t1, fillcolor=colour, opacity=0.45 if armed else 0.2, line_width=0, layer="below",
                      row="all", col=1)
        fig.add_annotation(x=(t0 + t1) / 2, y=1.0, yref="paper", yanchor="bottom", showarrow=False,
                           text=name + ("" if armed else " (disarmed)"), font=dict(size=10))
    fig.update_yaxes(range=[-0.5, 1.6], showticklabels=False, row=5, col=1)
    fig.update_xaxes(title_text="time since boot [s] (simulation time)", row=5, col=1)
    fig.update_layout(height=1050, hovermode="x unified", margin=dict(l=60, r=10, t=50, b=40),
                      legend=dict(orientation="v", x=1.01, y=1))
    return fig


def _png_data_uri(rgb: np.ndarray) -> str:
    import cv2

    ok, buf = cv2.imencode(".png", np.ascontiguousarray(rgb[..., ::-1]))
    if not ok:
        raise LogError("could not encode a frame as PNG")
    return "data:image/png;base64," + base64.b64encode(buf.tobytes()).decode()


def steps_figure(d):
    """Per view (a slider): camera frame with the projected grid, this view's p(occupied), the fused map."""
    import plotly.graph_objects as go
    from plotly.subplots import make_subplots

    from ..viz import draw_grid_overlay
    from .replay import _intrinsics_of

    n, T = d.grid.n, len(d.maps)
    acc, f1 = d.acc, d.f1
    fig = make_subplots(rows=1, cols=3, horizontal_spacing=0.06,
                        subplot_titles=("camera frame + grid at the reported pose",
                                        "this view: p(occupied) per cell (blank: not in view)",
                                        "fused map (o: truly occupied)"))
    per_step = []
    for t in range(T):
        traces = []
        img = d.images[t] if t < len(d.images) else None
        if img is not None:
            over = draw_grid_overlay(img, d.poses[t], d.grid, _intrinsics_of(img), d.labels, scale=2)
            traces.append((go.Image(source=_png_data_uri(over), name=f"frame {t + 1}"), 1))
        p = np.where(d.valid[t], d.p_occ[t], np.nan).reshape(n, n)
        traces.append((go.Heatmap(z=p, zmin=0, zmax=1, colorscale="Viridis", showscale=False, name=f"p_occ {t + 1}",
                                  hovertemplate="row %{y} col %{x}<br>p %{z:.3f}<extra></extra>"), 2))
        traces.append((go.Heatmap(z=np.asarray(d.maps[t]).reshape(n, n), zmin=0, zmax=1, colorscale="Viridis",
                                  colorbar=dict(title="p(occ)", len=0.8), name=f"fused {t + 1}",
                                  hovertemplate="row %{y} col %{x}<br>p %{z:.3f}<extra></extra>"), 3))
        per_step.append(traces)
    idx = []
    for t, traces in enumerate(per_step):
        for trace, col in traces:
            trace.visible = t == T - 1
            fig.add_trace(trace, 1, col)
            idx.append(t)
    rows, cols = np.nonzero(np.asarray(d.labels, bool).reshape(n, n))
    fig.add_trace(go.Scatter(x=cols, y=rows, mode="markers", marker=dict(symbol="circle-open", size=16, color="red",
                                                                         line=dict(width=2)),
                             name="truly occupied", hoverinfo="skip"), 1, 3)
    idx.append(-1)

    def title(t):
        return (f"view {t + 1} of {T}: Aacc so far {acc[t]:.3f}, F1 so far {f1[t]:.3f} "
                f"({d.fusion} fusion)")

    steps = [dict(method="update", label=str(t + 1),
                  args=[{"visible": [i == t or i == -1 for i in idx]}, {"title.text": title(t)}]) for t in range(T)]
    fig.update_layout(sliders=[dict(active=T - 1, steps=steps, currentvalue=dict(prefix="view "), pad=dict(t=30))],
                      title=dict(text=title(T - 1), x=0.01), height=520, margin=dict(l=10, r=10, t=80, b=10))
    for col in (2, 3):
        fig.update_yaxes(autorange="reversed", scaleanchor=f"x{col}", title_text="row (north up)", row=1, col=col)
        fig.update_xaxes(title_text="column", row=1, col=col)
    fig.update_xaxes(showticklabels=False, row=1, col=1)
    fig.update_yaxes(showticklabels=False, row=1, col=1)
    return fig


def metrics_figure(d):
    import plotly.graph_objects as go

    x = np.arange(1, len(d.maps) + 1)
    fig = go.Figure([go.Scatter(x=x, y=d.acc, name="Aacc", mode="lines+markers"),
                     go.Scatter(x=x, y=d.f1, name="F1", mode="lines+markers")])
    fig.update_layout(title="metrics after each view", xaxis_title="view", yaxis=dict(range=[0, 1.02]), height=320,
                      margin=dict(l=50, r=10, t=40, b=40))
    return fig


# --------------------------------------------------------------------------------------------------
# the page


def _summary_rows(rows: list[tuple[str, str]]) -> str:
    return "".join(f"<tr><th>{html.escape(k)}</th><td>{html.escape(v)}</td></tr>" for k, v in rows)


def write_flight_review(log, out=None, mission_file=None) -> Path:
    """Write the review page for a run directory or a bare .tlog; returns its path."""
    import plotly.io as pio

    from ..logs.flight_log import read_flight_log

    log = Path(log)
    run = None
    if log.is_dir():
        tlog = log / "telemetry.tlog"
        with warnings.catch_warnings(record=True) as caught:  # a damaged log: one line, as plain replay says it
            warnings.simplefilter("always")
            run = read_flight_log(log)
        for w in dict.fromkeys(str(w.message) for w in caught):
            print(f"uavsearch: warning: {w}", file=sys.stderr)
        out = Path(out) if out else log / "flight_review.html"
    else:
        tlog = log
        out = Path(out) if out else log.with_suffix(".html")
    first = ((run.header.get("team") or {}).get("system_ids") or [None])[0] if run else None
    tel = read_telemetry(tlog, first)
    home = run.header.get("home") if run else None
    if run is None and (log.parent / "search.jsonl").is_file():  # a run folder's own tlog: the flight's home
        from ..logs.flight_log import read_header

        home = read_header(log.parent).get("home")
    if home is None and mission_file:
        from ..fly.missions import load_mission

        home = load_mission(mission_file).home.model_dump()
    origin = _origin(tel, home)
    figs, rows, notes = [], [("log", str(log)), ("telemetry messages", str(tel.messages))], []
    views_enu = _enu(origin, [c[1] for c in tel.captures], [c[2] for c in tel.captures], [c[3] for c in tel.captures])
    view_truth, area_m, d = None, None, None
    if run is not None and run.steps:
        from .replay import replay_run_dir

        d = replay_run_dir(log)
        views_enu = d.positions_enu
        area_m = d.grid.n * d.grid.cell_m
        view_truth = [(s.sim_time_s, s.reported_position_enu, s.true_pose.position_enu)
                      for s in run.steps if s.true_pose]
        s = run.summary or {}
        rows += [("agent", str(run.header.get("agent", ""))), ("views", f"{len(run.steps)}"),
                 ("status", str(s.get("status", "unknown"))), ("end", str(s.get("end", ""))),
                 ("Aacc / F1 (final)", f"{d.acc[-1]:.3f} / {d.f1[-1]:.3f}"),
                 ("simulated time", f"{s['sim_time_s']:.1f} s" if s.get("sim_time_s") is not None else "n/a")]
        notes += d.warnings
    if tel.pos["t"]:
        rows.append(("flight", f"{tel.pos['t'][0]:.1f} - {tel.pos['t'][-1]:.1f} s since boot, max altitude "
                               f"{max(tel.pos['alt']) - origin.alt_m:.1f} m above home"))
    rows.append(("modes", " -> ".join(dict.fromkeys(m[1] for m in tel.modes)) or "none logged"))
    ids = (run.header.get("team") or {}).get("system_ids", []) if run else []
    team = {sid: read_telemetry(tlog, sid) for sid in ids[1:]}
    if team:
        notes.append(f"a team of {len(ids)}: the track shows every vehicle; the time series are vehicle "
                     f"{ids[0]}'s")
    figs.append(("Track", track_figure(tel, origin, views_enu, area_m, team)))
    figs.append(("Flight: altitude, velocity, attitude, estimator error, modes and events",
                 timeseries_figure(tel, origin, view_truth)))
    if d is not None:
        figs.append(("Search, view by view", steps_figure(d)))
        figs.append(("Search metrics", metrics_figure(d)))
    parts = []
    for i, (heading, fig) in enumerate(figs):
        div = pio.to_html(fig, full_html=False, include_plotlyjs=(i == 0), div_id=f"fig{i}",
                          config={"displaylogo": False, "responsive": True})
        parts.append(f"<h2>{html.escape(heading)}</h2>\n{div}")
    events = "".join(f"<tr><td>{t:.1f}</td><td>{html.escape(sev)}</td><td>{html.escape(text)}</td></tr>"
                     for t, sev, text in tel.events)
    title = f"Flight review: {log.name}"
    page = (f"<!DOCTYPE html>\n<html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
            "<style>body{font-family:sans-serif;margin:16px}table{border-collapse:collapse}"
            "th,td{border:1px solid #ccc;padding:2px 8px;text-align:left;font-size:13px}</style></head><body>"
            f"<h1>{html.escape(title)}</h1><table>{_summary_rows(rows)}</table>"
            + "".join(f"<p><b>note:</b> {html.escape(n)}</p>" for n in notes)
            + "\n".join(parts)
            + f"<h2>STATUSTEXT</h2><table><tr><th>t [s]</th><th>severity</th><th>text</th></tr>{events}</table>"
            + "</body></html>\n")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(page)
    return out


__all__ = ["Telemetry", "mode_name", "read_telemetry", "write_flight_review"]
