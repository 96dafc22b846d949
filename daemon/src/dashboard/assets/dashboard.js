// The dashboard's pages kept current from the daemon's job events (server-sent events of
// proto3 JSON `JobEvent`s, whose fields at their default values are left out).
"use strict";

(function () {
  const body = document.body;

  function stateName(state) {
    return String(state || "").replace(/^JOB_STATE_/, "").toLowerCase();
  }

  function duration(seconds) {
    const s = Math.max(0, Math.round(seconds));
    if (s < 60) return s + " s";
    if (s < 3600) return Math.floor(s / 60) + " min " + (s % 60) + " s";
    return Math.floor(s / 3600) + " h " + Math.floor((s % 3600) / 60) + " min";
  }

  // The time a running job has left at the pace of its frames so far, as the server
  // computes it.
  function eta(job, state) {
    const done = job.framesDone || 0;
    if (state !== "running" || done === 0) return "";
    const elapsed = (Date.now() - Number(job.createdUnixMs || 0)) / 1000;
    return duration((elapsed / done) * ((job.framesTotal || 0) - done));
  }

  // Updates what `root` (a row, or the job page) shows of `job`.
  function showJob(root, job) {
    const state = stateName(job.state);
    const cell = root.querySelector(".job-state");
    if (cell) {
      const badge = document.createElement("span");
      badge.className = "state state-" + state;
      badge.textContent = state;
      cell.replaceChildren(badge);
    }
    const progress = root.querySelector("progress");
    if (progress) {
      progress.max = job.framesTotal || 0;
      progress.value = job.framesDone || 0;
    }
    const frames = root.querySelector(".frames");
    if (frames) frames.textContent = (job.framesDone || 0) + "/" + (job.framesTotal || 0);
    const left = root.querySelector(".eta");
    if (left) left.textContent = eta(job, state);
    const priority = root.querySelector(".priority");
    if (priority) priority.textContent = job.priority || 0;
    // A job's page: the reason it waits holds only while it is queued, and each button
    // shows in the states it applies to.
    if (root === body) {
      if (state !== "queued") root.querySelectorAll(".waiting").forEach((e) => e.remove());
      root.querySelectorAll(".actions form").forEach((form) => {
        form.hidden = !form.dataset.when.split(" ").includes(state);
      });
    }
  }

  // The stage `root` shows, as the server words it with each event (`pages::job_stage`);
  // a job's page also follows its preview video ("waiting", "encoding", "ready", "failed").
  function showStage(root, event) {
    const cell = root.querySelector(".stage");
    if (cell) cell.textContent = event.stage || "";
    const preview = root.querySelector(".preview-video");
    if (preview && event.job.previewVideo) preview.textContent = event.job.previewVideo;
  }

  // Says in the header whether the page is following the farm; `data-live` is `open` once
  // the stream is.
  function showLive(state, text) {
    body.dataset.live = state;
    const live = document.querySelector(".live");
    if (live) live.textContent = text;
  }

  function listen(url, onEvent) {
    const source = new EventSource(url);
    source.addEventListener("open", () => showLive("open", "● live"));
    // EventSource reconnects by itself.
    source.addEventListener("error", () => showLive("reconnecting", "reconnecting…"));
    source.addEventListener("job", (message) => onEvent(JSON.parse(message.data)));
    // Events were missed: read everything again.
    source.addEventListener("resync", () => location.reload());
    return source;
  }

  function cell(row, content) {
    const td = document.createElement("td");
    if (content instanceof Node) td.appendChild(content);
    else td.textContent = content;
    row.appendChild(td);
    return td;
  }

  // The jobs list's filter as the server read it (`filter::JobQuery`): a state, labels that
  // a job must each have, a part of its name (lowercased).
  function listFilter() {
    return {
      state: body.dataset.filter || "",
      labels: JSON.parse(body.dataset.labels || "{}"),
      name: body.dataset.name || "",
    };
  }

  // Whether the list filtered by `filter` shows `job`, as the server decides.
  function takes(filter, job) {
    if (filter.state && stateName(job.state) !== filter.state) return false;
    const labels = job.labels || {};
    for (const key of Object.keys(filter.labels)) {
      if (labels[key] !== filter.labels[key]) return false;
    }
    const name = (job.name || job.requestId || "").toLowerCase();
    return !filter.name || name.includes(filter.name);
  }

  // The list filtered by `filter` and label `key`=`value` too (`JobQuery::query_with`).
  function narrowed(filter, key, value) {
    const query = new URLSearchParams();
    if (filter.state) query.append("state", filter.state);
    const labels = Object.entries(filter.labels);
    if (!(key in filter.labels)) labels.push([key, value]);
    labels.forEach(([k, v]) => query.append("label", k + "=" + v));
    if (filter.name) query.append("name", filter.name);
    return "/?" + query.toString();
  }

  // A job's labels as chips linking to the list narrowed by each (`html::label_chips`).
  function labelChips(filter, labels) {
    const span = document.createElement("span");
    span.className = "labels";
    Object.keys(labels || {}).sort().forEach((key) => {
      const chip = document.createElement("a");
      chip.className = "chip";
      chip.href = narrowed(filter, key, labels[key]);
      chip.textContent = key + "=" + labels[key];
      span.appendChild(chip);
    });
    return span;
  }

  // The row the server writes (`pages::job_row`); the dataset's name where another row
  // shows it.
  function jobRow(filter, job) {
    const row = document.createElement("tr");
    row.dataset.job = job.id;
    row.dataset.created = job.createdUnixMs || "0";
    const link = document.createElement("a");
    link.href = "/jobs/" + encodeURIComponent(job.id);
    link.textContent = job.id;
    cell(row, link);
    cell(row, job.name || job.requestId || "");
    cell(row, labelChips(filter, job.labels));
    const dataset = job.datasetId || "";
    const known = document.querySelector('td[data-dataset="' + CSS.escape(dataset) + '"]');
    cell(row, known ? known.textContent : dataset).dataset.dataset = dataset;
    cell(row, "").className = "job-state";
    cell(row, "").className = "stage";
    cell(row, document.createElement("progress"));
    cell(row, "").className = "frames";
    cell(row, "").className = "eta";
    return row;
  }

  function jobsPage() {
    const rows = document.querySelector("#jobs tbody");
    const count = document.querySelector(".count");
    const filter = listFilter();
    listen("/api/events", (event) => {
      const job = event.job;
      if (!job) return;
      let row = rows.querySelector('tr[data-job="' + CSS.escape(job.id) + '"]');
      if (!row) {
        if (!takes(filter, job)) return;
        row = jobRow(filter, job);
        rows.prepend(row);
        body.dataset.shown = Number(body.dataset.shown || 0) + 1;
        body.dataset.matching = Number(body.dataset.matching || 0) + 1;
        if (count) count.textContent = body.dataset.shown + " of " + body.dataset.matching + " jobs";
      }
      showJob(row, job);
      showStage(row, event);
    });
  }

  function jobPage() {
    const id = body.dataset.job;
    const grid = document.getElementById("frames");
    const showFrame = (frame) => {
      const index = frame.index || 0;
      const link = grid.querySelector('a[data-index="' + index + '"]');
      if (!link) return;
      const preview = Boolean(frame.preview);
      // A preview that arrives late never hides the final image.
      if (preview && link.dataset.state === "final") return;
      const version = preview ? "p" + (frame.completeness || 0).toFixed(3) : "final";
      const src = "/jobs/" + encodeURIComponent(id) + "/frames/" + index + "/thumbnail?v=" + version;
      let image = link.querySelector("img");
      if (!image) {
        image = document.createElement("img");
        image.alt = "frame " + index;
        link.querySelector(".placeholder").replaceWith(image);
      }
      if (image.getAttribute("src") !== src) image.setAttribute("src", src);
      link.dataset.state = preview ? "preview" : "final";
      link.querySelector(".caption").textContent = preview
        ? "#" + index + " · preview " + Math.round((frame.completeness || 0) * 100) + "%"
        : "#" + index;
    };
    listen("/api/events?job=" + encodeURIComponent(id), (event) => {
      if (event.job) {
        showJob(body, event.job);
        showStage(body, event);
        (event.job.frames || []).forEach(showFrame);
      }
      if (event.frame) showFrame(event.frame);
    });
  }

  function framePage() {
    const index = Number(body.dataset.frame);
    listen("/api/events?job=" + encodeURIComponent(body.dataset.job), (event) => {
      const frames = ((event.job && event.job.frames) || []).concat(event.frame ? [event.frame] : []);
      const news = frames.some((frame) => {
        if ((frame.index || 0) !== index) return false;
        const state = frame.preview ? "preview" : "final";
        return state !== body.dataset.state && body.dataset.state !== "final";
      });
      if (news) location.reload();
    });
  }

  // Buttons that cannot be undone ask first.
  document.querySelectorAll("form[data-confirm]").forEach((form) => {
    form.addEventListener("submit", (submit) => {
      if (!confirm(form.dataset.confirm)) submit.preventDefault();
    });
  });

  const pages = { jobs: jobsPage, job: jobPage, frame: framePage };
  if (pages[body.dataset.page]) pages[body.dataset.page]();
  const refresh = Number(body.dataset.refresh);
  if (refresh > 0) setTimeout(() => location.reload(), refresh * 1000);
})();
