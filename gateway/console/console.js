// EQA console: ask a question, watch an episode live, see the fleet and the homes. Plain JS, no library, no network but the
// gateway that served it. The token is kept in sessionStorage (this tab only) and sent as a bearer header.
"use strict";

(() => {
  const TOKEN_KEY = "eqa.token";
  const WATCH_PREFIX = "eqa.watch.";       // sessionStorage: events received per episode (resume after reload)
  const MAX_EVENTS = 5000;                 // events kept per episode (page and sessionStorage)
  const FLEET_PERIOD_MS = 1500;
  const IMAGE_PERIOD_MS = 400;             // at most one frame and one map fetch per period
  const RETRY_MS = [500, 1000, 2000];        // reconnect backoff (then every 2 s)

  const $ = (id) => document.getElementById(id);
  const letters = "ABCDEFGHIJKLMNOPQRSTUVWXYZ";

  // ---- token, requests, errors ------------------------------------------------------------------------
  let token = sessionStorage.getItem(TOKEN_KEY) || "";

  function headers(extra) {
    const h = Object.assign({}, extra || {});
    if (token) h["Authorization"] = "Bearer " + token;
    return h;
  }

  class ApiError extends Error {
    constructor(status, detail) {
      super(typeof detail === "string" ? detail : JSON.stringify(detail));
      this.status = status;
      this.detail = detail;
    }
  }

  function describe(err) {
    if (err instanceof ApiError) {
      if (err.status === 401) return "The gateway refused the token (" + err.message + "). Enter a token of EQA_API_TOKENS above.";
      if (err.status === 403) return "This token may not do that: " + err.message;
      if (err.status === 429) return "Too many requests: " + err.message + ". Retrying shortly.";
      if (err.status === 422 && Array.isArray(err.detail)) {
        return "Please correct: " + err.detail.map((d) => (d.loc || []).slice(1).join(".") + ": " + d.msg).join("; ");
      }
      return "The gateway answered " + err.status + ": " + err.message;
    }
    return "Cannot reach the gateway at " + location.origin + " (" + (err && err.message || err) +
      "). It may be stopped or restarting; the page retries by itself.";
  }

  let bannerKind = null;  // "auth" | "net" | "other"
  function showBanner(err) {
    const b = $("banner");
    b.textContent = describe(err);
    b.hidden = false;
    bannerKind = err instanceof ApiError ? (err.status === 401 ? "auth" : "other") : "net";
    b.className = bannerKind;
  }
  function clearBanner(kind) {
    if (kind && bannerKind !== kind && !(kind === "any")) return;
    $("banner").hidden = true;
    bannerKind = null;
  }

  // After a 401 the page makes no more authenticated calls until a new token is entered: the gateway counts
  // failed authentications per address and answers 429 to all of them after too many.
  let authBlocked = false;

  async function api(path, opts) {
    opts = opts || {};
    if (authBlocked && !opts.force && path !== "/v1/health") throw new ApiError(401, "waiting for a valid token");
    let r;
    try {
      r = await fetch(path, {method: opts.method || "GET", headers: headers(opts.headers), body: opts.body,
                             cache: "no-store"});
    } catch (e) {
      const err = new TypeError(e.message || "network error");
      showBanner(err);
      throw err;
    }
    if (bannerKind === "net") clearBanner("net");
    if (!r.ok) {
      let detail = r.statusText;
      try { detail = (await r.json()).detail; } catch (_) { /* not JSON */ }
      const err = new ApiError(r.status, detail);
      if (r.status === 401) authBlocked = true;
      if (r.status === 401 || r.status === 403 || r.status === 429 || r.status >= 500) showBanner(err);
      throw err;
    }
    if (bannerKind === "auth") clearBanner("auth");
    return r;
  }

  $("token-form").addEventListener("submit", async (ev) => {
    ev.preventDefault();
    token = $("token").value.trim();
    if (token) sessionStorage.setItem(TOKEN_KEY, token); else sessionStorage.removeItem(TOKEN_KEY);
    $("token").value = "";
    $("token-state").textContent = "checking ...";
    try {
      await api("/v1/fleet", {force: true});
      authBlocked = false;
      clearBanner("any");
      stopWatching();
      $("token-state").textContent = token ? "token accepted (kept for this tab)" : "no token (gateway without tokens)";
      route();
    } catch (e) {
      $("token-state").textContent = e instanceof ApiError && e.status === 401 ? "token refused" : "not checked";
      $("token").focus();
    }
  });
  function showTokenState() {
    $("token-state").textContent = token ? "token set for this tab" : "";
  }

  // ---- views and routing (#ask, #watch, #watch/<episode id>, #fleet, #homes, #homes/<name>) -----------------
  const VIEWS = ["ask", "watch", "fleet", "homes"];
  function route() {
    const hash = location.hash.replace(/^#/, "") || "ask";
    const [view, arg] = hash.split("/");
    const name = VIEWS.includes(view) ? view : "ask";
    for (const v of VIEWS) {
      $("view-" + v).hidden = v !== name;
      const link = $("nav-" + v);
      if (v === name) link.setAttribute("aria-current", "page"); else link.removeAttribute("aria-current");
    }
    document.title = "EQA console - " + name;
    if (name === "watch") {
      if (arg) watch(arg); else { stopWatching(); showRecent(); startRecent(); }
    } else {
      stopWatching();
    }
    if (name !== "watch" || arg) stopRecent();
    if (name === "fleet") startFleet(); else stopFleet();
    if (name === "homes") showHomes(arg ? decodeURIComponent(arg) : null);
  }
  window.addEventListener("hashchange", () => { route(); focusView(); });
  function focusView() {
    const hash = location.hash.replace(/^#/, "") || "ask";
    const t = $(hash.split("/")[0] + "-title");
    if (t) t.focus();
  }

  // ---- ask -------------------------------------------------------------------------------------------
  $("ask-form").addEventListener("submit", async (ev) => {
    ev.preventDefault();
    const body = {question: $("q-question").value.trim()};
    if (!body.question) {
      $("ask-state").textContent = "Please enter a question.";
      $("q-question").focus();
      return;
    }
    const choices = $("q-choices").value.split("\n").map((s) => s.trim()).filter(Boolean);
    if (choices.length) body.choices = choices;
    const scene = $("q-scene").value.trim();
    if (scene) body.scene = scene;
    body.strategy = $("q-strategy").value;
    body.stop_rule = $("q-stop").value;
    const eps = parseFloat($("q-eps").value);
    if (!Number.isNaN(eps)) body.eps = eps;
    const maxSteps = parseInt($("q-max-steps").value, 10);
    if (!Number.isNaN(maxSteps)) body.max_steps = maxSteps;
    const seed = parseInt($("q-seed").value, 10);
    if (!Number.isNaN(seed)) body.seed = seed;
    const home = $("q-home").value.trim();
    if (home) body.home = home;
    $("ask-submit").disabled = true;
    $("ask-state").textContent = "submitting ...";
    try {
      const r = await api("/v1/questions", {method: "POST", body: JSON.stringify(body),
                                            headers: {"Content-Type": "application/json"}});
      const sub = await r.json();
      $("ask-state").textContent = "episode " + sub.episode_id + " " + sub.state + " on " + sub.robot;
      location.hash = "#watch/" + sub.episode_id;
    } catch (e) {
      $("ask-state").textContent = describe(e);
    } finally {
      $("ask-submit").disabled = false;
    }
  });

  // ---- task (HELIOS pick-and-place / find-object) -------------------------------------------------------
  $("task-form").addEventListener("submit", async (ev) => {
    ev.preventDefault();
    const body = {instruction: $("t-instruction").value.trim(), ablation: $("t-ablation").value};
    if (!body.instruction) {
      $("task-state").textContent = "Please enter an instruction.";
      $("t-instruction").focus();
      return;
    }
    const scene = $("t-scene").value.trim();
    if (scene) body.scene = scene;
    const home = $("t-home").value.trim();
    if (home) body.home = home;
    for (const [id, key] of [["t-pick-limit", "pick_limit"], ["t-max-steps", "max_steps"], ["t-seed", "seed"]]) {
      const v = parseInt($(id).value, 10);
      if (!Number.isNaN(v)) body[key] = v;
    }
    $("task-submit").disabled = true;
    $("task-state").textContent = "submitting ...";
    try {
      const r = await api("/v1/tasks", {method: "POST", body: JSON.stringify(body),
                                        headers: {"Content-Type": "application/json"}});
      const sub = await r.json();
      $("task-state").textContent = "episode " + sub.episode_id + " " + sub.state + " on " + sub.robot;
      location.hash = "#watch/" + sub.episode_id;
    } catch (e) {
      $("task-state").textContent = describe(e);
    } finally {
      $("task-submit").disabled = false;
    }
  });

  // ---- watch: one episode's events, resumable ---------------------------------------------------------
  let w = null;  // the watched episode's state

  function stopWatching() {
    if (w) {
      save(w);
      w.stopped = true;
      if (w.abort) w.abort.abort();
      clearInterval(w.imageTimer);
    }
    w = null;
  }

  function load(eid) {
    try {
      const raw = sessionStorage.getItem(WATCH_PREFIX + eid);
      if (raw) {
        const s = JSON.parse(raw);
        if (s && Array.isArray(s.events)) return s;
      }
    } catch (_) { /* unreadable: start over */ }
    return {lastId: null, events: []};
  }
  function save(s) {
    if (!s) return;
    try {
      sessionStorage.setItem(WATCH_PREFIX + s.eid, JSON.stringify({lastId: s.lastId, events: s.events}));
    } catch (_) { /* storage full: a reload replays from the start instead */ }
  }
  window.addEventListener("pagehide", () => save(w));

  let recentTimer = null;
  function startRecent() {
    if (!recentTimer) recentTimer = setInterval(showRecent, FLEET_PERIOD_MS * 2);
  }
  function stopRecent() {
    clearInterval(recentTimer);
    recentTimer = null;
  }

  async function showRecent() {
    if (w) return;
    $("watch-pick").hidden = false;
    $("watch-episode").hidden = true;
    try {
      const r = await api("/v1/episodes?limit=20");
      const list = (await r.json()).episodes;
      if (w) return;  // an episode was opened meanwhile
      const ul = $("recent");
      ul.textContent = "";
      if (!list.length) ul.innerHTML = "<li>none yet: ask a question</li>";
      for (const ep of list) {
        const li = document.createElement("li");
        const a = document.createElement("a");
        a.href = "#watch/" + ep.episode_id;
        a.textContent = ep.episode_id;
        li.append(a, " " + ep.state + ": " + ep.question.text);
        ul.append(li);
      }
    } catch (_) { /* banner shown */ }
  }

  function watch(eid) {
    if (w && w.eid === eid) return;
    stopWatching();
    $("watch-pick").hidden = true;
    $("watch-episode").hidden = false;
    const saved = load(eid);
    w = {eid, lastId: saved.lastId, events: [], choices: [], maxSteps: null, step: -1, sets: [],
         ended: false, stopped: false, abort: null, imageTimer: null, lastFrameStep: -2, lastMapStep: -2, mapStep: -1,
         stepsSeen: -1, stopRule: null, eps: null, probs: {}, task: null, phases: []};
    $("w-log").textContent = "";
    $("w-set").textContent = "";
    $("w-set-history").textContent = "";
    $("w-answer").hidden = true;
    $("w-recording").hidden = true;
    $("w-task").hidden = true;
    for (const id of ["w-set-title", "w-set", "w-set-history"]) $(id).hidden = false;
    $("w-phase").textContent = "";
    $("w-phase-history").textContent = "";
    $("w-cancel").hidden = false;
    $("w-frame").removeAttribute("src");
    $("w-map").removeAttribute("src");
    $("w-question").textContent = eid;
    $("w-meta").textContent = "";
    setState("loading");
    for (const ev of saved.events) apply(ev.id, ev.data, true);
    w.lastId = saved.lastId;
    refreshStatus(w);
    stream(w);
    w.imageTimer = setInterval(() => images(w), IMAGE_PERIOD_MS);
  }

  async function refreshStatus(s) {
    try {
      const st = await (await api("/v1/episodes/" + encodeURIComponent(s.eid))).json();
      if (s !== w) return;
      $("w-question").textContent = st.question.text;
      if (!s.choices.length) s.choices = st.question.choices || [];
      if (st.task) showTask(s, st.task);
      s.maxSteps = s.maxSteps || st.max_steps;
      s.stopRule = st.stop.rule;
      s.eps = st.stop.eps;
      $("w-meta").textContent = s.eid + " on " + st.robot + ", scene " + st.question.scene + ", " + (st.task
        ? "task " + st.task.kind.replace("_", " ") + ", agent " + (st.ablation || "helios") + ", pick attempts " +
          (st.pick_limit || "unlimited")
        : st.strategy + ", stop rule " + st.stop.rule + (st.stop.rule === "cp" ? " (eps " + st.stop.eps + ")" : ""));
      if (!s.ended) setState(st.state);
      else if (st.outcome) setState(taskState(st.state, st.outcome));
      if (["stopped", "failed", "cancelled"].includes(st.state)) finalStatus(s, st);
      renderSteps(s);
    } catch (e) {
      if (e instanceof ApiError && e.status === 404) {
        s.stopped = true;
        setState("not found");
        $("w-question").textContent = "No episode " + s.eid + " (or it belongs to another token).";
      }
    }
  }

  // Read the SSE stream with fetch (EventSource cannot send the bearer header); on a lost connection
  // reconnect with Last-Event-ID = the last event applied, so every event is shown exactly once.
  async function stream(s) {
    let attempt = 0;
    while (!s.stopped && !s.ended) {
      if (authBlocked) { conn("waiting for a valid token"); return; }
      s.abort = new AbortController();
      const h = {Accept: "text/event-stream"};
      if (s.lastId) h["Last-Event-ID"] = s.lastId;
      try {
        const r = await fetch("/v1/episodes/" + encodeURIComponent(s.eid) + "/events",
                              {headers: headers(h), signal: s.abort.signal, cache: "no-store"});
        if (!r.ok) {
          let detail = r.statusText;
          try { detail = (await r.json()).detail; } catch (_) { /* not JSON */ }
          throw new ApiError(r.status, detail);
        }
        if (bannerKind) clearBanner("any");
        conn(attempt ? "reconnected (resumed after " + (s.lastId || "the start") + ")" : "live");
        attempt = 0;
        const reader = r.body.getReader();
        const dec = new TextDecoder();
        let buf = "";
        for (;;) {
          const {value, done} = await reader.read();
          if (done) break;
          buf += dec.decode(value, {stream: true});
          let cut;
          while ((cut = buf.indexOf("\n\n")) >= 0) {
            const block = buf.slice(0, cut);
            buf = buf.slice(cut + 2);
            let id = null;
            const data = [];
            for (const line of block.split("\n")) {
              if (line.startsWith("id:")) id = line.slice(3).trim();
              else if (line.startsWith("data:")) data.push(line.slice(5).replace(/^ /, ""));
            }
            if (data.length && !s.stopped) {
              apply(id, JSON.parse(data.join("\n")), false);
              s.lastId = id || s.lastId;
            }
          }
        }
        if (!s.ended && !s.stopped) throw new TypeError("the event stream closed");
      } catch (e) {
        if (s.stopped) return;
        if (e instanceof ApiError && [401, 403, 404, 422].includes(e.status)) {
          if (e.status === 401) authBlocked = true;
          showBanner(e);
          conn("stopped: " + describe(e));
          return;
        } else if (!(e instanceof ApiError)) {
          showBanner(e);
        }
        const wait = RETRY_MS[Math.min(attempt, RETRY_MS.length - 1)];
        attempt += 1;
        conn("connection lost; reconnecting in " + (wait / 1000) + " s (resumes after the last event)");
        await new Promise((res) => setTimeout(res, wait));
      }
    }
    if (s.ended) conn("episode ended");
    save(s);
  }

  function conn(text) { $("w-conn").textContent = text; }

  function setState(state) {
    const b = $("w-state");
    b.textContent = state;
    b.className = "badge " + state.replace(/\s/g, "-");
  }

  // A task that ended without achieving its goal is a failure whatever the episode's state says ("stopped"
  // only means it ran to its end).
  function taskState(state, outcome) {
    if (!outcome || state !== "stopped") return state;
    return outcome.success ? "task succeeded" : "task failed";
  }

  function numbersText(numbers) {  // the decision's numbers (Psi, Psi', IG, V, F0 ...) of a task goal
    const names = {Psi_prime: "Psi'"};
    const parts = Object.entries(numbers || {}).map(([k, v]) => (names[k] || k) + " " + Number(v).toPrecision(3));
    return parts.length ? " (" + parts.join(", ") + ")" : "";
  }

  function letterList(set) { return "{" + set.join(", ") + "}"; }

  // One event: the log line, then what it changes on the page.
  function apply(id, ev, replay) {
    const s = w;
    if (!s) return;
    if (id && s.events.length && s.events[s.events.length - 1].id === id) return;  // the same event twice
    s.events.push({id, data: ev});
    if (s.events.length > MAX_EVENTS) s.events.splice(0, s.events.length - MAX_EVENTS);
    const li = document.createElement("li");
    li.dataset.id = id || "";
    li.dataset.kind = ev.kind;
    if (ev.step !== undefined && ev.step !== null) li.dataset.step = ev.step;
    li.textContent = (ev.step !== undefined && ev.step !== null ? "step " + ev.step + " " : "") + ev.kind +
      (ev.reason ? ": " + ev.reason : "") + (ev.kind === "decision" && ev.prediction_set && ev.prediction_set.length
        ? " set " + letterList(ev.prediction_set) : "");
    const log = $("w-log");
    log.append(li);
    while (log.childElementCount > MAX_EVENTS) log.firstElementChild.remove();
    switch (ev.kind) {
      case "episode_start":
        s.choices = ev.choices || [];
        s.maxSteps = ev.max_steps;
        s.stopRule = ev.stop && ev.stop.rule;
        s.eps = ev.stop && ev.stop.eps;
        if (ev.question) $("w-question").textContent = ev.question;
        setState("running");
        break;
      case "started":
        setState("running");
        break;
      case "frame":
        s.step = Math.max(s.step, ev.step);
        if (ev.skill) {
          li.textContent += ": " + ev.skill.skill + (ev.skill.success ? " succeeded" : " failed") +
            (ev.skill.reason ? " (" + ev.skill.reason + ")" : "");
        }
        break;
      case "map_update":  // the map and the frame's prompt points of this step exist now
        s.mapStep = Math.max(s.mapStep, ev.step);
        break;
      case "goal":
        if (ev.phase) {
          $("w-task").hidden = false;
          s.phases.push(ev.phase);
          $("w-phase").textContent = "phase: " + ev.phase + (ev.skill ? ", next skill " + ev.skill : "") +
            (ev.target !== undefined && ev.target !== null ? " on #" + ev.target : "") + numbersText(ev.numbers);
          $("w-phase").dataset.phase = ev.phase;
          $("w-phase-history").textContent = "phases so far: " + compress(s.phases).join(" > ");
          li.textContent += ": " + ev.phase;
        }
        break;
      case "step_scores":
        s.probs = {};
        (ev.answer_probs || []).forEach((p, i) => { s.probs[letters[i]] = p; });
        if (!s.choices.length && ev.choices) s.choices = ev.choices;
        break;
      case "decision":
        s.stepsSeen = Math.max(s.stepsSeen, ev.step);
        if (ev.rule === "cp") {  // the running intersection of the CP sets (may end empty)
          s.sets.push(ev.prediction_set || []);
          renderSet(s, ev.prediction_set || []);
        } else {
          renderSet(s, null, ev.reason);
        }
        break;
      case "episode_end":
        s.ended = true;
        $("w-cancel").hidden = true;
        setState(taskState(ev.state, ev.outcome));
        if (s.stopRule === "cp" || (ev.prediction_set && ev.prediction_set.length)) renderSet(s, ev.prediction_set || []);
        showAnswer(s, ev);
        if (!replay) refreshStatus(s);
        images(s, true);
        break;
      case "failed":
      case "cancelled":
        setState(ev.kind);
        break;
      default:
        break;
    }
    renderSteps(s);
  }

  function renderSteps(s) {
    const done = Math.max(s.step, s.stepsSeen) + 1;
    const T = s.maxSteps || "?";
    $("w-steps").textContent = "step " + done + " of " + T;
    const p = $("w-progress");
    p.max = s.maxSteps || 1;
    p.value = Math.min(done, p.max);
  }

  function renderSet(s, set, note) {
    const ul = $("w-set");
    ul.textContent = "";
    const labels = s.choices.length ? s.choices.map((_, i) => letters[i]) : (set || []);
    for (const L of labels) {
      const li = document.createElement("li");
      const inSet = set ? set.includes(L) : true;
      li.className = inSet ? "in" : "out";
      li.dataset.letter = L;
      const text = s.choices[letters.indexOf(L)];
      li.textContent = L + (text ? ") " + text : "");
      li.setAttribute("aria-label", L + (text ? " " + text : "") + (inSet ? ", in the set" : ", ruled out"));
      ul.append(li);
    }
    ul.dataset.set = set ? set.join("") : "";
    const hist = s.sets.map(letterList);
    $("w-set-history").textContent = set ? "after each step: " + compress(hist).join(" > ") +
      (set.length ? "" : " (empty: no answer is consistent at this coverage)")
      : (note ? "(" + note + ")" : "");
  }

  function compress(list) {  // "{A, B} x3 > {B}" instead of repeating unchanged sets
    const out = [];
    let prev = null, n = 0;
    for (const x of list) {
      if (x === prev) { n += 1; continue; }
      if (prev !== null) out.push(n > 1 ? prev + " x" + n : prev);
      prev = x; n = 1;
    }
    if (prev !== null) out.push(n > 1 ? prev + " x" + n : prev);
    return out;
  }

  function showAnswer(s, ev) {
    const box = $("w-answer");
    box.hidden = false;
    box.textContent = "";
    const h = document.createElement("p");
    h.className = "final";
    box.classList.remove("fail");
    if (s.task) {
      const out = ev.outcome;
      const sr = ev.metrics ? ev.metrics.SR : undefined;
      const ok = out ? out.success : sr === undefined ? null : Boolean(sr);
      h.textContent = "Task " + (ok === null ? (ev.state || "ended") : ok ? "succeeded" : "failed") +
        (out && !out.success ? ": " + out.text.replace(/^failed: /, "") : "");
      if (ok === false || ev.state === "failed" || ev.state === "cancelled") box.classList.add("fail");
      box.dataset.outcome = ok === null ? "" : ok ? "success" : "failure";
    } else if (ev.answer) {
      h.textContent = "Answer: " + ev.answer + ") " + (ev.answer_text || "");
    } else {
      h.textContent = "No answer (" + (ev.state || "ended") + ")";
    }
    box.append(h);
    const conf = document.createElement("p");
    conf.id = "w-confidence";
    const parts = [];
    if (s.stopRule === "cp" && ev.prediction_set && ev.prediction_set.length && s.eps) {
      parts.push("prediction set " + letterList(ev.prediction_set) + " holds the true answer with probability >= " +
                 Math.round((1 - s.eps) * 100) + " % (conformal prediction, eps " + s.eps + ")");
    }
    if (s.stopRule === "cp" && ev.prediction_set && !ev.prediction_set.length) {
      parts.push("none: the prediction set is empty, no answer is consistent at " + Math.round((1 - s.eps) * 100) +
                 " % coverage");
    }
    if (ev.answer && s.probs[ev.answer] !== undefined) {
      parts.push("scorer's probability of " + ev.answer + " at the last step: " + Number(s.probs[ev.answer]).toFixed(2));
    }
    conf.textContent = "Confidence: " + (parts.length ? parts.join("; ") : "not stated");
    if (!s.task) box.append(conf);
    if (ev.metrics && Object.keys(ev.metrics).length) {
      const m = document.createElement("p");
      m.id = "w-metrics";
      m.textContent = "Task metrics: " + Object.entries(ev.metrics).map(([k, v]) => k + " " + v).join(", ");
      box.append(m);
    }
    const why = document.createElement("p");
    why.className = "muted";
    why.textContent = (ev.steps !== undefined ? ev.steps + " of " + ev.max_steps + " steps. " : "") + (ev.reason || "");
    box.append(why);
    $("w-recording").hidden = false;
    const file = s.eid + ".rrd";
    $("w-rerun").textContent =
      "curl -H \"Authorization: Bearer $EQA_TOKEN\" -o " + file + " " + location.origin + "/v1/episodes/" +
      s.eid + "/recording\nrerun " + file;
    if (!box.dataset.focused) { box.dataset.focused = "1"; }
  }

  $("w-download").addEventListener("click", async () => {
    if (!w) return;
    const eid = w.eid;
    try {
      const r = await api("/v1/episodes/" + encodeURIComponent(eid) + "/recording");
      const url = URL.createObjectURL(await r.blob());
      const a = document.createElement("a");
      a.href = url;
      a.download = eid + ".rrd";
      document.body.append(a);
      a.click();
      a.remove();
      setTimeout(() => URL.revokeObjectURL(url), 60000);
    } catch (e) {
      conn(e instanceof ApiError && e.status === 404 ? "no recording of this episode (record was off?)" : describe(e));
    }
  });

  $("w-cancel").addEventListener("click", async () => {
    if (!w) return;
    try { await api("/v1/episodes/" + encodeURIComponent(w.eid), {method: "DELETE"}); }
    catch (e) { conn(describe(e)); }
  });

  // The latest camera view and map, fetched with the token into blob URLs, only when their step changed.
  async function images(s, force) {
    if (s !== w || s.busy || authBlocked) return;
    s.busy = true;
    try {
      for (const [kind, key, cap] of [["frame", "lastFrameStep", "camera view"], ["map", "lastMapStep", "map"]]) {
        if (!force && s[key] >= s.mapStep) continue;  // fetched once the step's map (and prompt points) is in
        const r = await fetch("/v1/episodes/" + encodeURIComponent(s.eid) + "/" + kind + ".png",
                              {headers: headers(), cache: "no-store"});
        if (r.status === 401) { authBlocked = true; return; }
        if (!r.ok) continue;
        const step = parseInt(r.headers.get("X-EQA-Step"), 10);
        if (s !== w) return;
        if (step === s[key] && !force) continue;
        s[key] = step;
        const img = $("w-" + kind);
        const old = img.src;
        img.src = URL.createObjectURL(await r.blob());
        img.alt = (kind === "frame" ? "camera view with prompt points" : "top-down map") + " at step " + step;
        img.dataset.step = step;
        $("w-" + kind + "-cap").textContent = cap + " at step " + step;
        if (old && old.startsWith("blob:")) URL.revokeObjectURL(old);
      }
    } catch (_) {
      /* the stream reports connection problems */
    } finally {
      s.busy = false;
    }
    if (s.ended && s === w && !force) clearInterval(s.imageTimer);
  }

  function showTask(s, task) {
    s.task = task;
    $("w-task").hidden = false;
    for (const id of ["w-set-title", "w-set", "w-set-history"]) $(id).hidden = true;  // a task has no answer set
    if (!$("w-phase").textContent) $("w-phase").textContent = "task " + task.kind + ": " + task.text;
  }

  function finalStatus(s, st) {
    if (!s.ended && st.state !== "stopped") return;
    if (st.answer && !$("w-answer").hidden) return;
    showAnswer(s, {answer: st.answer, answer_text: st.answer_text, prediction_set: st.prediction_set,
                   steps: st.steps, max_steps: st.max_steps, reason: st.stop_reason, state: st.state,
                   metrics: st.metrics, outcome: st.outcome});
  }

  // ---- fleet -----------------------------------------------------------------------------------------
  let fleetTimer = null;
  function startFleet() {
    if (fleetTimer) return;
    fleet();
    fleetTimer = setInterval(fleet, FLEET_PERIOD_MS);
  }
  function stopFleet() {
    clearInterval(fleetTimer);
    fleetTimer = null;
  }

  function cell(tr, text, cls) {
    const td = document.createElement("td");
    td.textContent = text;
    if (cls) td.className = cls;
    tr.append(td);
    return td;
  }

  async function fleet() {
    let f;
    try {
      f = await (await api("/v1/fleet")).json();
    } catch (e) {
      $("f-updated").textContent = "not updated: " + describe(e);
      return;
    }
    $("f-updated").textContent = "updated " + new Date(f.at * 1000).toLocaleTimeString();
    $("f-rate").textContent = f.episodes_per_minute + " episodes per minute (" + f.finished_recently +
      " ended in the last 5 minutes)";
    const rb = document.querySelector("#f-robots tbody");
    rb.textContent = "";
    for (const r of f.robots) {
      const tr = document.createElement("tr");
      tr.dataset.robot = r.robot;
      cell(tr, r.robot);
      const td = cell(tr, "");
      if (r.episode_id && r.episode_id !== "busy") {
        const a = document.createElement("a");
        a.href = "#watch/" + r.episode_id;
        a.textContent = r.episode_id;
        td.append(a);
      } else {
        td.textContent = r.episode_id || "idle";
      }
      cell(tr, r.step !== null && r.step !== undefined ? r.step + " / " + r.max_steps : "");
      cell(tr, r.question || "");
      cell(tr, r.queue.length ? r.queue.length + ": " + r.queue.join(", ") : "empty");
      rb.append(tr);
    }
    const sb = document.querySelector("#f-services tbody");
    sb.textContent = "";
    const kinds = new Set([...Object.keys(f.services), ...f.missing]);
    for (const k of [...kinds].sort()) {
      const tr = document.createElement("tr");
      const inst = f.services[k] || [];
      tr.dataset.service = k;
      tr.dataset.alive = inst.length;
      tr.className = inst.length ? "ok" : "down";
      cell(tr, k);
      cell(tr, inst.length ? String(inst.length) : "none alive: episodes cannot run", inst.length ? "" : "bad");
      cell(tr, inst.join(", "));
      sb.append(tr);
    }
    const fl = $("f-failures");
    fl.textContent = "";
    if (!f.recent_failures.length) fl.innerHTML = "<li>none</li>";
    for (const x of f.recent_failures) {
      const li = document.createElement("li");
      const a = document.createElement("a");
      a.href = "#watch/" + x.episode_id;
      a.textContent = x.episode_id;
      li.append(a, " on " + x.robot + " at " + new Date(x.at * 1000).toLocaleTimeString() + ": " + x.reason);
      fl.append(li);
    }
  }

  // ---- homes: the token's homes and one home's memory ---------------------------------------------------
  function bytesText(n) {
    if (n < 1024) return n + " B";
    if (n < 1024 * 1024) return (n / 1024).toFixed(1) + " KiB";
    return (n / 1024 / 1024).toFixed(1) + " MiB";
  }
  function ageText(s) {
    if (s < 120) return Math.round(s) + " s";
    if (s < 7200) return Math.round(s / 60) + " min";
    if (s < 172800) return Math.round(s / 3600) + " h";
    return Math.round(s / 86400) + " days";
  }
  let homeShown = null;  // the name of the home on the page (a reset asks twice)

  async function showHomes(name) {
    $("homes-pick").hidden = !!name;
    $("home-one").hidden = !name;
    if (name) return showHome(name);
    homeShown = null;
    let list;
    try {
      list = await (await api("/v1/homes?limit=200")).json();
    } catch (e) {
      $("h-count").textContent = "not loaded: " + describe(e);
      return;
    }
    $("h-count").textContent = list.total ? list.total + " homes of this token" :
      "no homes yet: give a home name when you ask a question";
    const tb = document.querySelector("#h-list tbody");
    tb.textContent = "";
    for (const h of list.homes) {
      const tr = document.createElement("tr");
      tr.dataset.home = h.name;
      const a = document.createElement("a");
      a.href = "#homes/" + encodeURIComponent(h.name);
      a.textContent = h.name;
      cell(tr, "").append(a);
      cell(tr, h.memory ? String(h.memory.views) : "none yet");
      cell(tr, h.memory ? bytesText(h.memory.bytes) : "");
      cell(tr, String(h.episodes_submitted));
      cell(tr, ageText(h.age_s));
      cell(tr, h.active_episodes.length ? h.active_episodes.length + " running or queued" : "idle");
      tb.append(tr);
    }
  }

  function term(dl, name, value) {
    const dt = document.createElement("dt");
    dt.textContent = name;
    const dd = document.createElement("dd");
    dd.textContent = value;
    dd.dataset.term = name;
    dl.append(dt, dd);
  }

  async function showHome(name) {
    if (homeShown !== name) {
      $("h-reset").textContent = "Reset home";
      $("h-reset").classList.remove("confirm");
      $("h-reset-state").textContent = "";
    }
    homeShown = name;
    $("h-name").textContent = "Home " + name;
    let h;
    try {
      h = await (await api("/v1/homes/" + encodeURIComponent(name))).json();
    } catch (e) {
      $("h-summary").textContent = "";
      $("h-name").textContent = e instanceof ApiError && e.status === 404 ? "No home " + name + " of this token"
        : "Home " + name + " not loaded: " + describe(e);
      $("h-active").textContent = "";
      $("h-parts").textContent = "";
      $("h-map-fig").hidden = true;
      return;
    }
    if (homeShown !== name) return;
    const dl = $("h-summary");
    dl.textContent = "";
    const m = h.memory;
    term(dl, "house", h.house || "the robot's own world (no scene)");
    term(dl, "views", m ? String(m.views) : "none yet (no episode of it mapped)");
    term(dl, "size", m ? bytesText(m.bytes) : "0 B");
    term(dl, "episodes mapped", m ? String(m.episodes) : "0");
    term(dl, "episodes submitted", String(h.episodes_submitted));
    term(dl, "age", ageText(h.age_s));
    term(dl, "last used", new Date(h.last_used_at * 1000).toLocaleString());
    if (m) term(dl, "scenes", m.scenes.join(", ") || "none");
    const ul = $("h-active");
    ul.textContent = "";
    if (!h.active_episodes.length) ul.innerHTML = "<li>none</li>";
    for (const eid of h.active_episodes) {
      const li = document.createElement("li");
      const a = document.createElement("a");
      a.href = "#watch/" + eid;
      a.textContent = eid;
      li.append(a);
      ul.append(li);
    }
    $("h-parts").textContent = h.parts && h.parts.length ? h.parts.join(", ") : "nothing stored yet";
    $("h-map-fig").hidden = !h.map_png;
    if (h.map_png) {
      const r = await fetch(h.map_png, {headers: headers(), cache: "no-store"});
      if (r.ok && homeShown === name) {
        const img = $("h-map");
        const old = img.src;
        img.src = URL.createObjectURL(await r.blob());
        if (old && old.startsWith("blob:")) URL.revokeObjectURL(old);
      }
    }
  }

  $("h-reset").addEventListener("click", async () => {
    const name = homeShown;
    const b = $("h-reset");
    if (!name) return;
    if (!b.classList.contains("confirm")) {  // the first press only asks
      b.classList.add("confirm");
      b.textContent = "Really reset " + name + "? Its memory is deleted";
      $("h-reset-state").textContent = "press again to reset";
      return;
    }
    b.classList.remove("confirm");
    b.textContent = "Reset home";
    try {
      const r = await (await api("/v1/homes/" + encodeURIComponent(name), {method: "DELETE"})).json();
      $("h-reset-state").textContent = "home " + r.name + " reset (" + r.deleted_keys + " stored parts deleted)";
      homeShown = null;
      $("home-one").hidden = true;
      $("homes-pick").hidden = false;
      history.replaceState(null, "", "#homes");
      await showHomes(null);
      $("h-count").textContent = "home " + r.name + " reset. " + $("h-count").textContent;
    } catch (e) {
      $("h-reset-state").textContent = e instanceof ApiError && e.status === 409 ? "not reset: " + e.message
        : describe(e);
    }
  });

  // ---- start -----------------------------------------------------------------------------------------
  showTokenState();
  route();
  // Tell about an unreachable gateway or a refused token at once, not only on the first action.
  api("/v1/fleet").catch(() => { /* banner shown */ });
  setInterval(() => { if (bannerKind === "net") api("/v1/health").catch(() => {}); }, 3000);
})();
