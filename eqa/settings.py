"""All configuration, read from ``EQA_*`` environment variables in one class.

Lists (endpoints, tokens) are comma-separated. Nothing deep in the code reads the environment: services
receive a :class:`Settings` instance and keep the groups of it they declare (:func:`view`; a service's
``settings_groups``, the gateway's ``gateway.app.SETTINGS_GROUPS``), so each reads only its own knobs.
``docker-compose.yml`` sets exactly these variables (a test checks).
"""

from __future__ import annotations

import functools
import os
import socket
from pathlib import Path
from typing import Annotated, Any, ClassVar, Literal

from pydantic import Field, field_validator, model_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

CsvList = Annotated[list[str], NoDecode]
# Distributions rmw_zenoh_cpp is released for (docs/robots.md names the versions the bridge speaks to)
ROS2_DISTROS = ("humble", "jazzy", "kilted", "rolling")
Ros2Distro = Literal["humble", "jazzy", "kilted", "rolling"]


def default_instance() -> str:
    host = "".join(c if c.isalnum() or c in "_-" else "-" for c in socket.gethostname())[:40]
    return f"{host}-{os.getpid()}"


class SettingsGroup(BaseSettings):
    """One group of settings; each group reads its own ``EQA_*`` variables and can be built on its own."""

    model_config = SettingsConfigDict(env_prefix="EQA_", extra="ignore")

    @field_validator("zenoh_listen", "zenoh_connect", "api_tokens", "cors_origins", "robots", "ros2_robots",
                     "ros2_distros", mode="before", check_fields=False)
    @classmethod
    def _split_csv(cls, v: object) -> object:
        if isinstance(v, str):
            return [p.strip() for p in v.split(",") if p.strip()]
        return v


class ProcessSettings(SettingsGroup):
    """One process of the fleet: its id, logging, data directory, parent."""

    # --- process ---
    instance: str = Field(default_factory=default_instance, description="this process' instance id")
    log_level: str = "INFO"
    data_dir: Path = Path("var")
    parent_pid: int = Field(
        default=0, ge=0,
        description="a service exits when this process is no longer its parent (the launcher sets it to its own pid, "
        "so a killed launcher leaves no orphaned services); 0 = never (containers, systemd, a shell)",
    )

    @property
    def recordings_path(self) -> Path:
        return self.data_dir / "recordings"


class BusSettings(SettingsGroup):
    """The Zenoh bus: mode, endpoints, security, robot sharding among instances (eqa/bus.py, eqa/security.py,
    eqa/sharding.py).
    """

    # --- bus ---
    zenoh_mode: Literal["peer", "client", "router"] = "peer"
    zenoh_listen: CsvList = Field(default_factory=list, description="endpoints to listen on, e.g. tcp/127.0.0.1:7447")
    zenoh_connect: CsvList = Field(default_factory=lambda: ["tcp/127.0.0.1:7447"])
    zenoh_multicast: bool = False
    # bus security (eqa/security.py): mTLS, user/password, the stream-ownership ACL. All off by default.
    zenoh_tls_ca: Path | None = Field(default=None, description="CA certificate (PEM); set = tls/ links only, mTLS")
    zenoh_tls_cert: Path | None = Field(default=None, description="this node's certificate; its CN is its role")
    zenoh_tls_key: Path | None = Field(default=None, description="this node's private key (PEM)")
    zenoh_user: str | None = Field(default=None, description="user name (= role) this node authenticates with")
    zenoh_password: str | None = Field(default=None, description="its password")
    zenoh_users_file: Path | None = Field(default=None, description="user:password lines a router accepts")
    zenoh_acl: bool = Field(default=False, description="enforce the stream-ownership ACL on this node (routers)")
    zenoh_tls_dir: Path | None = Field(default=None, description="eqa up: dir of <role>.pem/.key + ca.pem (eqa certs)")
    # robot sharding among instances of a stateful service (eqa/sharding.py)
    shard: bool = Field(default=True, description="share robots among live instances of a service (rendezvous hash)")
    bus_link_wait_s: float = Field(
        default=5.0, ge=0,
        description="a session with EQA_ZENOH_CONNECT endpoints waits this long at open for its first link, so its "
        "first liveliness query and publications reach the fleet (then it goes on and keeps retrying); 0 = no wait",
    )


class StoreSettings(SettingsGroup):
    """The state store (eqa/store.py)."""

    # --- store ---
    redis_url: str | None = Field(default=None, description="redis://host:port/db; unset = embedded SQLite store")


class FleetSettings(SettingsGroup):
    """Robots and step delivery: which robots the simulator drives, re-sending and re-driving a step, standbys."""

    # --- fleet ---
    robots: CsvList = Field(default_factory=lambda: ["robot0"])
    step_resend_s: float = Field(
        default=30.0, ge=0,
        description="the sim sends a step's frame again when no goal came back after this long (a message lost "
        "while a service restarted); the others answer a repeated step by re-publishing their output; keep it "
        "above the slowest step (a slow VLM), 0 = never",
    )
    step_resends_max: int = Field(default=3, ge=0, description="resends of one step before the sim gives up")
    episode_timeout_s: float = Field(
        default=120.0, gt=0,
        description="no-progress time before an episode fails (the gateway's watchdog; the sim does not resume a "
        "stored episode older than this)")
    step_redrive: bool = Field(
        default=True,
        description="when an instance of a stateful service (re)appears, the sim sends the current frame of the "
        "robots it now owns at once instead of waiting for EQA_STEP_RESEND_S",
    )
    # warm standby processes (eqa/standby.py, eqa/launcher.py; docs/reliability.md)
    standby: bool = Field(
        default=True,
        description="the launcher keeps one pre-started standby process per service (imports done, off the bus) "
        "and promotes it the moment the active instance dies, instead of starting a new process",
    )


class SimulatorSettings(SettingsGroup):
    """The simulator: scenes and camera (services/sim)."""

    # --- simulator ---
    scenes_dir: Path | None = None  # default data_dir/scenes
    sim_width: int = Field(default=640, ge=16, le=4096)
    sim_height: int = Field(default=480, ge=12, le=4096)
    hm3d_dir: Path | None = None

    @property
    def scenes_path(self) -> Path:
        """``scenes_dir``, else ``data_dir/scenes``: read together with :class:`ProcessSettings`."""
        return self.scenes_dir or self.data_dir / "scenes"  # type: ignore[attr-defined]


class ScorerSettings(SettingsGroup):
    """The VLM scorer pool and its backends (services/vlm_scorer)."""

    # --- scorer ---
    scorer_backend: Literal["oracle", "hf", "remote"] = "oracle"
    scorer_timeout_s: float = Field(default=20.0, gt=0)
    scorer_replica: str | None = None  # replica id; default = instance
    scorer_batch_max: int = Field(default=1, ge=1, le=64, description=(
        "dynamic batching in a replica: up to this many queued requests (of any robots) in one backend call; "
        "1 = off"))
    scorer_batch_window_ms: float = Field(default=0.0, ge=0.0, le=1000.0, description=(
        "how long a batch's first request waits for batch mates (ms), and only while the batch holds fewer "
        "requests than were in flight when the previous batch was answered (a lone robot waits for no one); "
        "0 = only those already queued"))
    hf_model_path: Path | None = None
    hf_device: str = "cpu"
    remote_base_url: str | None = None
    remote_model: str | None = None
    remote_api_key: str | None = None
    remote_timeout_s: float = Field(default=30.0, gt=0)
    remote_max_retries: int = Field(default=4, ge=0)
    # endpoints without chat-completions logprobs (services/vlm_scorer/backends/remote.py)
    remote_mode: Literal["auto", "logprobs", "sampling"] = Field(
        default="auto", description="auto: logprobs, or sampling when the endpoint returns none (decided once)"
    )
    remote_samples: int = Field(default=8, ge=1, le=64, description="sampled completions per query (sampling)")
    remote_sample_temperature: float = Field(default=1.0, gt=0.0, le=2.0)


class SimulatedPerceptionSettings(SettingsGroup):
    """Knobs of the simulated perception model (the oracle scorer, not a VLM; services/vlm_scorer/backends/oracle.py
    documents each). Benchmark settings, not deployment settings.
    """

    # --- simulated perception model ---
    oracle_accuracy: float = Field(default=0.85, ge=0.0, le=1.0)
    # simulated perception model (services/vlm_scorer/backends/oracle.py documents each knob)
    oracle_evidence_confidence: float = Field(default=0.8, gt=0.0, lt=1.0)
    oracle_bias_confidence: float = Field(default=0.7, gt=0.0, lt=1.0)
    oracle_temperature: float = Field(default=1.0, gt=0.0, description=">1 flatter, <1 over-confident")
    oracle_relevance_scale: float = Field(default=0.55, gt=0.0, le=1.0)
    oracle_min_pixels_frac: float = Field(default=0.0005, ge=0.0, lt=1.0, description="share of image: unseen below")
    oracle_full_pixels_frac: float = Field(default=0.005, gt=0.0, le=1.0, description="share of image: fully seen")
    oracle_max_range_m: float = Field(default=6.0, gt=0.0, description="distance past which a target is unseen")
    # miscalibration modes of the simulated perception model, 0 = off (oracle.py documents each)
    oracle_miscal_category: float = Field(default=0.0, ge=0.0, le=1.0, description="Rel varies by question category")
    oracle_miscal_view: float = Field(default=0.0, ge=0.0, le=1.0, description="Rel varies by view clutter")
    oracle_miscal_related: float = Field(default=0.0, ge=0.0, le=1.0, description="related-but-wrong object taken")
    oracle_miscal_irrelevant: float = Field(default=0.0, ge=0.0, le=1.0, description="confident no-evidence answers")
    # presence queries ("is there an X in this image?", "is this the Y?"), oracle.py documents each
    oracle_presence_miss: float = Field(default=0.15, ge=0.0, le=1.0, description="P(an instance is never recognised)")
    oracle_presence_false_yes: float = Field(default=0.1, ge=0.0, le=1.0, description="P(hallucinated yes) per view")
    oracle_presence_room_error: float = Field(default=0.1, ge=0.0, le=1.0, description="P(wrong room answer) per view")
    oracle_presence_confidence: float = Field(default=0.85, ge=0.5, lt=1.0, description="mean P of the answer given")


class PlannerSettings(SettingsGroup):
    """Exploration: Eq. A6 temperatures and the value layers' view bins (services/planner,
    services/mapper/semantic_map.py).
    """

    # --- planner ---
    tau_lsv: float = 1.0
    tau_gsv: float = 1.0
    tau_sv: float = 1.0
    tau_sv_normal: float = 1.0
    # view orientation in the value layers (services/mapper/semantic_map.py). 0 = off
    view_bins: int = Field(default=0, ge=0, le=16, description="viewing-direction bins per value layer, 0 = off")
    view_agree: int = Field(default=2, ge=1, le=16, description="bins that must see a cell before a value below "
                            "neutral (LSV < 1/|P|) is believed")


class StopperSettings(SettingsGroup):
    """Stopping and answering: the CP table, answer memory, object evidence (services/stopper)."""

    # --- stopper ---
    calibration_name: str = Field(default="default", description="CP calibration table name (eqa calibrate)")
    # answer from the K most relevant views (services/stopper/answer_memory.py); 0 = the paper's
    # single-view answer. A CP table must be calibrated with the same rule (eqa calibrate --answer-memory K).
    answer_memory_k: int = Field(default=0, ge=0, le=16, description="answer memory: views pooled, 0 = off")
    answer_memory_fusion: Literal["loglinear", "linear"] = Field(
        default="loglinear", description="answer memory pooling: relevance-weighted log-linear or linear")
    # joint mode: the MAPPER keeps the answer_memory_views most relevant views and asks
    # the scorer pool for ONE answer over all of them (several images in one prompt; hf backend only); the
    # step's StepScores.answer_probs is that joint answer. "fusion" (default) leaves the mapper alone and the
    # stopper pools per-view distributions (answer_memory_k). Use joint with answer_memory_k = 0.
    answer_memory_mode: Literal["fusion", "joint"] = Field(
        default="fusion", description="answer memory: stopper fusion, or one multi-image prompt (mapper, hf only)")
    answer_memory_views: int = Field(default=4, ge=1, le=16, description="joint mode: views in the prompt (K)")
    # question episodes track the target class in the HELIOS object layer and the stopper
    # combines its evidence with the VLM's answer (services/stopper/object_evidence.py); off by default.
    object_evidence: bool = Field(default=False, description="object evidence for existence/counting questions")
    # chosen on the tuning seed 11 (eqa_app/benches/object_evidence.py eval; bench/results/answer_rules_objects.json)
    object_evidence_psi_min: float = Field(default=0.1, ge=0.0, le=1.0, description="Psi from which an instance counts")
    object_evidence_weight: float = Field(default=0.75, ge=0.0, le=1.0, description="the layer's weight in the pool")
    # counting across views: a counting question's answer pools the VLM's f with the count of the object layer's
    # instances (fused over every view so far) within 0.3 m of the asked room's extent on the robot's own map
    # (IN_ROOM votes; the whole map when no room is asked), psi_min and w as above. On by default: it met the
    # declared bar (p < 0.01 at T on both strategies), seeds 1-3, oracle scorer and simulated detector: success
    # at T 0.729 vs 0.583 (semantic, p 0.0066), 0.740 vs 0.490 (fbe, p 3e-6), n = 96 counting questions each
    # (docs/results/closed-world-answers.md). Cost per step of a counting question: one detection request and
    # its fusion into the layer, and one IN_ROOM yes/no prompt when a room is asked. "frame": the single-view
    # answer. A CP table must be calibrated with the same rule (the stopper notes a mismatch).
    answer_counting: Literal["views", "frame"] = Field(
        default="views", description="counting questions: count across views in the asked room, or one frame")


class GatewaySettings(SettingsGroup):
    """The HTTP gateway: address, tokens, limits, queues, retention, hostile clients (gateway/, docs/security.md)."""

    # --- gateway ---
    gateway_host: str = "127.0.0.1"
    gateway_port: int = Field(default=8080, ge=0, le=65535)
    api_tokens: CsvList = Field(
        default_factory=list,
        description="bearer tokens, each 'token' or 'token:scope+scope' with scopes submit, read, admin (a bare "
        "token has submit+read: it submits and sees its own episodes; admin sees and cancels all); empty = auth off",
    )
    rate_limit_per_s: float = Field(default=50.0, gt=0)
    auth_failures_per_min: float = Field(
        default=20.0, gt=0, description="failed authentications one client address may make per minute (then 429)"
    )
    max_body_bytes: int = Field(default=2 * 1024 * 1024, ge=1024, le=64 * 1024 * 1024, description="HTTP body cap")
    queue_max_per_robot: int = Field(default=50, ge=0, le=100_000, description="queued episodes per robot (429)")
    queue_max_per_token: int = Field(
        default=20, ge=1, le=100_000, description="queued + running episodes per token (429)"
    )
    episode_retention_count: int = Field(
        default=50_000, ge=10, description="stored episode records kept (the oldest ended ones are deleted)"
    )
    episode_retention_days: float = Field(default=30.0, gt=0, description="ended episodes older than this go")
    cors_origins: CsvList = Field(default_factory=list)
    busy_policy: Literal["queue", "refuse"] = "queue"
    trusted_proxies: CsvList = Field(
        default_factory=list,
        description="CIDRs of reverse proxies whose X-Forwarded-For names the client (e.g. 10.0.0.0/8); empty = the "
        "client is the TCP peer, X-Forwarded-For is ignored",
    )
    auth_failures_per_prefix_per_min: float = Field(
        default=60.0, gt=0, description="failed authentications per minute with tokens of one 6-character prefix "
        "(from any address; then 429 for wrong tokens of that prefix)",
    )
    body_timeout_s: float = Field(
        default=10.0, gt=0, le=3600, description="a request body must arrive whole within this (else 408, closed)"
    )
    max_concurrent_uploads: int = Field(
        default=32, ge=1, le=100_000, description="request bodies read at once (more get 503 with Retry-After)"
    )
    sse_max_per_token: int = Field(
        default=16, ge=1, le=100_000, description="open event streams (SSE) per token (more get 429)"
    )
    gateway_keep_alive_s: float = Field(
        default=5.0, gt=0, le=600, description="idle HTTP keep-alive connections are closed after this"
    )
    gateway_shutdown_grace_s: float = Field(
        default=3.0, gt=0, le=600,
        description="on SIGTERM, requests in flight may finish for this long before they are cancelled; an open "
        "event stream never finishes by itself (its client resumes with Last-Event-ID), so without this bound a "
        "follower of a running episode keeps the gateway from exiting",
    )

    @field_validator("trusted_proxies", mode="before")
    @classmethod
    def _proxy_cidrs(cls, v: object) -> object:
        import ipaddress

        items = [p.strip() for p in v.split(",") if p.strip()] if isinstance(v, str) else v
        if isinstance(items, list):
            for item in items:
                try:
                    ipaddress.ip_network(str(item), strict=False)
                except ValueError as exc:
                    raise ValueError(f"EQA_TRUSTED_PROXIES: {item!r} is not an address or CIDR (e.g. 10.0.0.0/8)"
                                     ) from exc
        return items


class HeliosSettings(SettingsGroup):
    """HELIOS tasks and planning (paper Table 3 defaults; services/planner/helios.py, task_fsm.py)."""

    # --- HELIOS ---
    helios_alpha_cs: float = Field(default=1.0, ge=0.0, description="alpha_cs: uncertainty weight, Eq. 7/11")
    helios_alpha_d: float = Field(
        default=0.05, ge=0.0, description="alpha_d: distance weight, Eq. 8/10 (per metre; with "
        "EQA_HELIOS_VALUE_SCALE=best, the share of the step's best benefit a metre costs; Table 3: 0.001 on the "
        "paper's scale; 0.05 with best chosen on tuning seed 11, docs/results/helios-tasks.md)")
    helios_value_scale: Literal["paper", "best"] = Field(
        default="best", description="Eq. 10's benefits S IG and F F0 as they are (paper) or over the step's largest "
        "(best), so that alpha_d weighs distance whatever the scale of IG (services/planner/helios.py:values; "
        "chosen on tuning seed 11)")
    helios_path_clearance: Literal["levels", "cut"] = Field(
        default="levels", description="task paths: planned at the planner's clearance levels and cut at the mapped "
        "clearance (levels), or planned only at levels that keep the mapped clearance (cut; fewer successes on "
        "tuning seed 11, docs/results/helios-tasks.md)")
    helios_deadline: Literal["commit", "off"] = Field(
        default="commit", description="when the steps left are only enough to reach the best known candidate of "
        "the phase's class, act on it (place while holding, stop in an object search, pick without a pick limit) "
        "rather than run out of steps (commit), or keep to the paper's rule to the end (off); chosen on tuning "
        "seed 11, docs/results/helios-tasks.md")
    helios_distance: Literal["straight", "path"] = Field(
        default="straight", description="dist of Eq. 10 from the robot to a frontier or candidate: the straight "
        "line (straight) or the length of the way on the map at the planner's clearance levels (path, "
        "services/planner/task_step.py:travel_distances); straight chosen on tuning seed 11, "
        "docs/results/helios-tasks.md")
    helios_max_looks: int = Field(
        default=3, ge=1, le=12, description="gaze points one candidate is looked at from before the look rule "
        "(Eq. 11) passes to the next (this implementation's bound; chosen on tuning seed 11)")
    helios_tau_g: float = Field(default=0.4, description="tau_g: Psi_g threshold to pick the object (Table 3: 0.5; "
                                "0.4 chosen on tuning seed 11, docs/results/helios-tables.md)")
    helios_tau_stop: float = Field(default=0.6, description="tau_g of an object search: Psi_g threshold to stop at "
                                   "the object (section 4.2; Table 3: 0.5; chosen on tuning seed 11, "
                                   "docs/results/helios-tables.md)")
    helios_tau_b: float = Field(default=0.5, description="tau_b: Psi_b threshold to place on a goal receptacle")
    helios_tau_inc: float = Field(default=0.05, ge=0.0, description="tau_inc: least gain in Psi to look again")
    helios_od_a: float = Field(default=0.35, ge=0.0, le=1.0, description="detector threshold, start receptacle")
    helios_od_g: float = Field(default=0.25, ge=0.0, le=1.0, description="detector threshold, object")
    helios_od_b: float = Field(default=0.45, ge=0.0, le=1.0, description="detector threshold, goal receptacle")
    helios_cs_a: float = Field(default=0.3, ge=0.0, le=1.0, description="cs_a: S to be a start receptacle candidate")
    helios_cs_g: float = Field(default=0.3, ge=0.0, le=1.0, description="cs_g: S to be an object candidate")
    helios_cs_b: float = Field(default=0.3, ge=0.0, le=1.0, description="cs_b: S to be a goal receptacle candidate")
    helios_alpha_cpa: float = Field(default=3.0, gt=0.0, description="alpha_cpa: concentration update scaling")
    helios_pick_attempts: int = Field(default=0, ge=0, description="pick attempts allowed (0 = unlimited)")
    helios_gaze_radius_m: float = Field(default=0.9, gt=0.0, description="gaze points: contour distance")
    helios_gaze_points: int = Field(default=12, ge=1, le=256, description="gaze points on the contour")
    helios_gaze_obstacle_m: float = Field(default=1.0, ge=0.0, description="gaze: taller obstacles on the way occlude")


class ObjectLayerSettings(SettingsGroup):
    """The HELIOS object layer and the detector backend (services/mapper/objects, services/vlm_scorer/detector)."""

    # --- HELIOS object layer and detector ---
    detector_backend: Literal["oracle", "hf", "remote"] = Field(
        default="oracle", description="open-vocabulary detector of the scorer pool (remote: no standard protocol)"
    )
    detector_model_path: Path | None = Field(default=None, description="hf detector: OWL-ViT / OWLv2 directory")
    detector_ground_truth: bool = Field(
        default=False, description="oracle detector as ground-truth semantics (HELIOS Table 4 yardstick)"
    )
    helios_device: str = Field(default="cpu", description="torch device of the object layer (cpu, cuda)")
    helios_render_scale: float = Field(default=0.5, ge=0.05, le=1.0, description="object layer works at this scale")
    helios_max_gaussians: int = Field(default=60_000, ge=1, le=5_000_000, description="Gaussians kept per episode")
    helios_max_new_per_frame: int = Field(default=6_000, ge=0, le=1_000_000, description="Gaussians made per frame")
    helios_max_instances: int = Field(default=64, ge=0, le=4096, description="instances published per map update")
    helios_gaze_width: int = Field(default=96, ge=16, le=1024, description="optimistic-view render width (Eq. 11/12)")


class SimulatedDetectorSettings(SettingsGroup):
    """Knobs of the simulated detector (not a real detector; services/vlm_scorer/detector/oracle.py documents each).
    Benchmark settings, not deployment settings.
    """

    # --- simulated detector ---
    # simulated detector (services/vlm_scorer/detector/oracle.py documents each knob)
    detector_oracle_recall: float = Field(default=0.9, ge=0.0, le=1.0)
    detector_oracle_confusion: float = Field(default=0.12, ge=0.0, le=1.0)
    detector_oracle_similar_fp: float = Field(default=0.15, ge=0.0, le=1.0)
    detector_oracle_background_fp: float = Field(default=0.08, ge=0.0, le=1.0)
    detector_oracle_bleed_frac: float = Field(default=0.015, ge=0.0, le=0.2)


class MonitoringSettings(SettingsGroup):
    """Rerun recording and live viewing, Prometheus metrics, structured logs (eqa/metrics.py, eqa/logs.py,
    docs/metrics.md).
    """

    # --- monitoring ---
    rerun_url: str | None = Field(default=None, description="rerun+http://host:9876/proxy for live viewing")
    record: bool = True
    log_format: Literal["text", "json"] = Field(
        default="text", description="json: one JSON object per log line with service, episode, robot, step")
    metrics_port: int = Field(
        default=0, ge=0, le=65535,
        description="a service process serves Prometheus /metrics on this port (0 = off); the launcher gives "
        "itself this port and each child the next ones; the gateway serves /metrics on its own port")
    metrics_host: str = Field(default="127.0.0.1", description="address the metrics port binds (0.0.0.0 in compose)")
    metrics_token: str | None = Field(
        default=None, description="bearer token for the gateway's /metrics from other hosts (with EQA_API_TOKENS "
        "set; loopback callers and admin tokens need none)")


class Ros2Settings(SettingsGroup):
    """The ROS 2 bridge (services/ros2_bridge; the robot contract is docs/robots.md)."""

    # --- ROS 2 bridge ---
    ros2_robots: CsvList = Field(default_factory=list, description="robots a ROS 2 robot on rmw_zenoh drives "
                                 "through the bridge; the sim leaves them alone")
    ros2_domain_id: int = Field(default=0, ge=0, le=232, description="ROS_DOMAIN_ID of the robots")
    ros2_distro: Ros2Distro = Field(default="jazzy", description="ROS 2 distribution of the robots (rmw_zenoh key "
                                    "form: humble has no type hashes)")
    ros2_distros: CsvList = Field(default_factory=list, description="per-robot distributions that differ from "
                                  "EQA_ROS2_DISTRO, e.g. robot1=humble,robot2=rolling")
    ros2_namespace: str = Field(default="/{robot}", max_length=200,
                                description="ROS namespace of a robot's topics; {robot} is the robot's name")
    ros2_rgb_topic: str = Field(default="camera/color/image_raw", description="sensor_msgs/Image, rgb8 or bgr8")
    ros2_depth_topic: str = Field(default="camera/depth/image_raw",
                                  description="sensor_msgs/Image, 16UC1 (EQA_ROS2_DEPTH_UNIT_M) or 32FC1 metres")
    ros2_info_topic: str = Field(default="camera/color/camera_info", description="sensor_msgs/CameraInfo")
    ros2_pose_topic: str = Field(default="odom", description="base pose: nav_msgs/Odometry, or tf2_msgs/TFMessage")
    ros2_pose_type: Literal["odometry", "tf"] = "odometry"
    ros2_map_frame: str = Field(default="map", description="the world frame of poses and goals")
    ros2_base_frame: str = Field(default="base_link", description="child frame of the base pose (TF)")
    ros2_goal_topic: str = Field(default="goal_pose", description="geometry_msgs/PoseStamped goals (Nav2's topic)")
    ros2_depth_unit_m: float = Field(default=0.001, gt=0, le=1.0, description="metres per 16UC1 depth unit")
    ros2_camera_height_m: float = Field(default=1.5, ge=0.0, le=5.0, description="camera above the base")
    ros2_camera_tilt_deg: float = Field(default=-30.0, ge=-90.0, le=90.0, description="camera pitch, negative down")
    ros2_arrive_tolerance_m: float = Field(default=0.25, gt=0, le=5.0)
    ros2_arrive_yaw_tolerance_deg: float = Field(default=20.0, gt=0, le=180.0)
    ros2_settle_s: float = Field(default=0.5, ge=0.0, le=30.0,
                                 description="the pose must stay within tolerance this long to count as arrived")
    ros2_goal_timeout_s: float = Field(default=60.0, gt=0, le=3600.0,
                                       description="a goal not reached in this time is refused to the planner")
    ros2_frame_timeout_s: float = Field(default=5.0, gt=0, le=300.0,
                                        description="time to get a fresh, consistent RGB-D frame after arrival")
    ros2_max_stamp_age_s: float = Field(default=2.0, gt=0, le=600.0, description="older stamps are stale")
    ros2_max_stamp_skew_s: float = Field(default=0.5, gt=0, le=60.0,
                                         description="colour, depth and pose stamps of one frame at most this apart")
    ros2_max_image_pixels: int = Field(default=4_194_304, ge=1, le=67_108_864)
    ros2_pick_place_service: str = Field(default="", max_length=200, description="the robot's pick/place hook "
                                         "(docs/robots.md); empty: task episodes are refused on its robots")

    @field_validator("ros2_distros")
    @classmethod
    def _robot_distros(cls, v: list[str]) -> list[str]:
        for item in v:
            robot, sep, distro = item.partition("=")
            if not sep or not robot.strip() or distro.strip() not in ROS2_DISTROS:
                raise ValueError(f"EQA_ROS2_DISTROS entry {item!r}: want robot=distro with distro one of "
                                 f"{', '.join(ROS2_DISTROS)}")
        return [i.replace(" ", "") for i in v]

    def ros2_distro_of(self, robot: str) -> str:
        """The ROS 2 distribution of one robot."""
        for item in self.ros2_distros:
            name, _, distro = item.partition("=")
            if name == robot:
                return distro
        return self.ros2_distro


class HomeSettings(SettingsGroup):
    """Homes: a house's memory across episodes, its bounds and retention (eqa/homes.py, gateway/homes.py)."""

    # --- homes ---
    homes_max_per_tenant: int = Field(
        default=100, ge=1, le=100_000,
        description="homes one tenant may hold (a question or task naming a new home past it gets 429; delete one "
        "with DELETE /v1/homes/{name})",
    )
    homes_max_bytes_per_tenant: int = Field(
        default=2 * 1024 * 1024 * 1024, ge=1024, le=1024 * 1024 * 1024 * 1024,
        description="bytes one tenant's homes may hold together: an episode naming a home is admitted only if the "
        "tenant's other homes (their stored bytes; EQA_HOME_MAX_BYTES for those with an episode queued or running) "
        "plus EQA_HOME_MAX_BYTES for this one fit (429 otherwise; delete a home with DELETE /v1/homes/{name}); at "
        "least EQA_HOME_MAX_BYTES",
    )
    homes_retention_days: float = Field(
        default=90.0, gt=0,
        description="a home no episode has used for this long is deleted with its memory (the gateway's watchdog)",
    )
    # the mapper's home memory and warm start (services/mapper/home_memory.py, home_shell.py)
    home_max_views: int = Field(
        default=24, ge=0, le=256,
        description="view memory of a home: keyframes kept (greedy max-coverage of observed floor cells); 0 = "
        "a home keeps its map only",
    )
    home_max_bytes: int = Field(
        default=64 * 1024 * 1024, ge=1024, le=4 * 1024 * 1024 * 1024,
        description="bytes of a home's stored parts (map and views) at most; views that do not fit are not kept, a "
        "map that alone does not fit is not stored",
    )
    home_warm_views: int = Field(
        default=24, ge=0, le=256,
        description="warm start: remembered views re-scored for a new question in a known home (the most covering "
        "first); 0 = the map is carried over but no memory steps",
    )
    home_redetect_views: int = Field(
        default=8, ge=0, le=256,
        description="a task in a home: remembered views re-detected at its first frame for its classes no earlier "
        "task asked for (the most covering first; services/mapper/home_objects.py); 0 = none (8 chosen on tuning "
        "seed 11: docs/homes.md)",
    )
    home_restore_objects: Literal["evidence", "all"] = Field(
        default="evidence",
        description="a task in a home: which Gaussians of the home's object layer it starts with: 'evidence' = "
        "those holding evidence for one of its classes (HELIOS creates Gaussians only inside detected task-class "
        "pixels, appendix 6.1); 'all' = every one, those without such evidence at the flat prior (chosen on tuning "
        "seed 11: docs/homes.md)",
    )
    home_memory_steps: int = Field(
        default=0, ge=0, le=256,
        description="warm start: of the re-scored views, the stopper gets this many as memory steps, the most "
        "relevant ones (Rel, Eq. 5; every re-scored view still writes its semantic values); 0 = all of them",
    )
    home_warm_timeout_s: float = Field(
        default=20.0, gt=0, le=600,
        description="warm start: the re-scoring of the view memory waits this long at most; views not scored by "
        "then are left out of the episode's memory steps",
    )
    home_warm_parallel: int = Field(
        default=4, ge=1, le=32,
        description="warm start: score requests of remembered views in flight at once (the scorer pool batches "
        "concurrent requests)",
    )
    home_warm_budget: float = Field(
        default=0.15, ge=0.0, le=1.0,
        description="warm start: a question in a home whose map explored part of the house gets appendix B's step "
        "budget for the floor left, 3 sqrt(A - A_explored) with A = (max_steps / 3)^2 (eqa/budget.py), and at "
        "least this share of max_steps for looking again (0.15 chosen on tuning seed 11: docs/homes.md); 1 = the full "
        "max_steps",
    )
    home_warm_area: Literal["explored", "observed"] = Field(
        default="observed",
        description="warm start: the floor A_e the home map already covers, which the warm budget subtracts: "
        "'observed' = floor columns the map has seen with the full camera, inside the house "
        "(services.mapper.home_memory.observed_floor; chosen on tuning seed 11: docs/homes.md); 'explored' = columns "
        "with an appendix-B explored voxel (narrow view)",
    )
    home_ttl_s: float = Field(
        default=90 * 24 * 3600.0, gt=0,
        description="a home's stored parts expire this long after the last episode that updated it (keep it at "
        "least EQA_HOMES_RETENTION_DAYS, after which the gateway deletes an unused home)",
    )
    home_stale_weight: float = Field(
        default=0.0, ge=0.0, le=1.0,
        description="warm start: a remembered view older than a change the robot saw (a frame contradicting the "
        "view's geometry) or than EQA_HOME_STALE_AGE_S gives the stopper its evidence with its relevance times "
        "this (0 = it constrains nothing: the robot looks again; 1 = stale evidence counts in full, no change check)",
    )
    home_stale_age_s: float = Field(
        default=0.0, ge=0.0,
        description="warm start: a remembered view older than this (seconds) is stale (EQA_HOME_STALE_WEIGHT); "
        "0 = no age limit, only observed changes make a view stale",
    )
    home_calibration_name: str = Field(
        default="",
        description="CP calibration table of warm starts (questions whose home held memory; the first question in "
        "an empty home is cold and uses EQA_CALIBRATION_NAME), calibrated on warm traces of the same memory bounds; "
        "empty = none: warm questions stop on the cold table and their decisions and answer say they are not "
        "calibrated for warm starts",
    )


class Settings(
    ProcessSettings, BusSettings, StoreSettings, FleetSettings, SimulatorSettings, ScorerSettings,
    SimulatedPerceptionSettings, PlannerSettings, StopperSettings, GatewaySettings, HeliosSettings,
    ObjectLayerSettings, SimulatedDetectorSettings, MonitoringSettings, Ros2Settings, HomeSettings,
):
    """All settings: every group, one flat namespace (``settings.sim_width``), each ``EQA_*`` variable read and
    validated once (the validators that relate groups are here).

    A component declares the groups it reads and keeps only those (:func:`view`): a service may be handed the
    whole object and narrows it at construction, so a knob of another group is an ``AttributeError`` there, not a
    value that silently works. The groups also keep the simulated perception models' knobs (benchmark settings)
    apart from deployment settings."""

    @model_validator(mode="after")
    def _one_answer_rule(self) -> Settings:
        """Joint answers already come from the K most relevant views; pooling them again in the stopper would be
        a rule nobody calibrated."""
        if self.answer_memory_mode == "joint" and self.answer_memory_k > 0:
            raise ValueError(
                "EQA_ANSWER_MEMORY_MODE=joint takes its views from EQA_ANSWER_MEMORY_VIEWS; set EQA_ANSWER_MEMORY_K=0 "
                "(the stopper's fusion of per-view answers is the other answer-memory mode, not an addition to it)"
            )
        return self

    @model_validator(mode="after")
    def _tenant_bytes_hold_a_home(self) -> Settings:
        """One home may grow to EQA_HOME_MAX_BYTES: a tenant bound below it would refuse every episode in a home."""
        if self.homes_max_bytes_per_tenant < self.home_max_bytes:
            raise ValueError(
                f"EQA_HOMES_MAX_BYTES_PER_TENANT={self.homes_max_bytes_per_tenant} is below EQA_HOME_MAX_BYTES="
                f"{self.home_max_bytes} (one home's bound): no episode could name a home; raise it or lower "
                "EQA_HOME_MAX_BYTES")
        return self

    def env(self) -> dict[str, str]:
        """This configuration as ``EQA_*`` variables (to hand to child processes)."""
        out: dict[str, str] = {}
        for name, value in self.model_dump().items():
            if value is None:
                continue
            if isinstance(value, list):
                value = ",".join(value)
            out[f"EQA_{name.upper()}"] = str(value)
        return out


def env_names() -> set[str]:
    """Every environment variable the code reads."""
    return {f"EQA_{name.upper()}" for name in Settings.model_fields}


Groups = tuple[type[SettingsGroup], ...]
GROUPS: Groups = tuple(k for k in Settings.__mro__ if isinstance(k, type) and issubclass(k, SettingsGroup)
                       and k not in (Settings, SettingsGroup))


class SettingOutsideGroupsError(AttributeError):
    """A read of a setting whose group the component did not declare."""


class SettingsView(SettingsGroup):
    """Base of the narrowed settings :func:`view` makes: read-only, and a read of a field of a group it was not
    made with names that group."""

    model_config = SettingsConfigDict(frozen=True)
    groups: ClassVar[Groups] = ()

    def __reduce__(self) -> tuple[Any, ...]:
        """Pickled by its groups and values (its class is made at run time, under no importable name)."""
        return _rebuild, (self.groups, dict(self.__dict__))

    def __getattr__(self, name: str) -> Any:
        try:
            return super().__getattr__(name)  # type: ignore[misc]
        except AttributeError:
            owner = next((g for g in GROUPS if name in g.model_fields or name in vars(g)), None)
            if owner is None:
                raise
            raise SettingOutsideGroupsError(
                f"{name} is a setting of {owner.__name__}, which this component does not declare (it reads "
                f"{', '.join(g.__name__ for g in self.groups)})", name=name, obj=self) from None


def view_class(groups: Groups) -> type[SettingsView]:
    """The settings class of exactly ``groups`` (whatever their order), made once per set of groups."""
    unknown = [g for g in groups if g not in GROUPS]
    if unknown:
        raise TypeError(f"not settings groups: {unknown}")
    return _view_class(tuple(g for g in GROUPS if g in groups))


@functools.cache
def _view_class(bases: Groups) -> type[SettingsView]:
    name = "Settings[" + ",".join(g.__name__.removesuffix("Settings") for g in bases) + "]"
    return type(name, (SettingsView, *bases), {"__module__": __name__, "groups": bases})


def _rebuild(groups: Groups, values: dict[str, Any]) -> SettingsView:
    return view_class(groups).model_construct(**values)


def view(settings: SettingsGroup, groups: Groups) -> SettingsView:
    """``settings`` restricted to ``groups``: their fields with ``settings``' values (validated already, the
    environment is not read again), and nothing else. ``settings`` may be a :class:`Settings` or a view holding
    at least these groups; a view of exactly these groups is returned as it is."""
    cls = view_class(groups)
    if type(settings) is cls:
        return settings  # type: ignore[return-value]
    return cls.model_construct(**{name: getattr(settings, name) for name in cls.model_fields})
