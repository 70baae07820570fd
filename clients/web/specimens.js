// The specimens to pick from: each with its overview's thumbnail, its ROIs and pixel size, and its
// build state; builds submitted over HTTP (/api/jobs) with their progress while they run. The
// list asks the server again every few seconds while a build is queued or running.
import { formatNumber } from "./plot.js";

const POLL_BUSY_MS = 1000;
const POLL_IDLE_MS = 5000; // a build a lab system submits shows within 5 s

export class SpecimenList {
  // `api(path)` fetches from the server; `token` (or null) goes into the thumbnails' URLs;
  // `onPick(id)` opens a specimen; `onBuilt(id)` is told when a build under way has finished.
  constructor({ element, api, token, onPick, onBuilt }) {
    Object.assign(this, { element, api, token, onPick, onBuilt });
    this.specimens = [];
    this.jobs = [];
    this.current = null;
    this.timer = null;
    // Each specimen's thumbnail <img>, kept across redraws while its summary is the same: a poll
    // redraws the list, and a new <img> would ask the server to draw the thumbnail again.
    this.pictures = new Map();
  }

  // Reads the specimens and the jobs again and redraws; returns the specimens' summaries.
  async refresh() {
    const [specimens, jobs] = await Promise.all([this.getJson("/api/specimens", []), this.getJson("/api/jobs", { jobs: [] })]);
    const running = new Set(this.jobs.filter(isUnderWay).map((job) => job.job_id));
    this.specimens = specimens;
    this.jobs = jobs.jobs;
    for (const job of this.jobs) if (running.has(job.job_id) && job.state === "succeeded") this.onBuilt(job.specimen_id);
    this.render();
    clearTimeout(this.timer);
    this.timer = setTimeout(() => this.refresh(), this.jobs.some(isUnderWay) ? POLL_BUSY_MS : POLL_IDLE_MS);
    return this.specimens;
  }

  async getJson(path, fallback) {
    const response = await this.api(path);
    return response.ok ? response.json() : fallback;
  }

  // The latest job of a specimen, or undefined.
  jobOf(id) {
    return this.jobs.filter((job) => job.specimen_id === id).sort((a, b) => a.created.localeCompare(b.created)).at(-1);
  }

  select(id) {
    this.current = id;
    this.render();
  }

  render() {
    const built = new Set(this.specimens.map((s) => s.id));
    const building = [...new Set(this.jobs.map((job) => job.specimen_id))].filter((id) => !built.has(id));
    const entries = [...this.specimens.map((s) => this.entry(s.id, s)), ...building.map((id) => this.entry(id, null))];
    if (!entries.length) {
      const empty = document.createElement("p");
      empty.className = "specimen-empty";
      empty.textContent = "no specimens yet: run fracto reconstruct, or submit a build to /api/jobs";
      entries.push(empty);
    }
    this.element.replaceChildren(...entries);
  }

  // The thumbnail of a built specimen: the one shown before unless its summary changed (rebuilt).
  picture(id, summary) {
    const key = JSON.stringify(summary);
    const kept = this.pictures.get(id);
    if (kept?.key === key) return kept.picture;
    const picture = document.createElement("img");
    picture.src = `/api/specimens/${id}/thumbnail` + (this.token ? `?token=${encodeURIComponent(this.token)}` : "");
    picture.alt = "";
    this.pictures.set(id, { key, picture });
    return picture;
  }

  // One entry: a button that opens a built specimen; a build's state and progress below.
  entry(id, summary) {
    const item = document.createElement("button");
    item.type = "button";
    item.className = "specimen";
    item.dataset.specimen = id;
    item.disabled = !summary;
    item.classList.toggle("current", id === this.current);
    const picture = summary ? this.picture(id, summary) : document.createElement("div");
    picture.className = "thumbnail";
    const name = document.createElement("strong");
    name.textContent = id;
    const details = document.createElement("span");
    details.className = "specimen-details";
    if (summary) {
      const overview = summary.rois[0];
      details.textContent = `${summary.rois.length} ROI · ${formatNumber(overview.pixel_size_um)} µm/px`;
    }
    const state = document.createElement("span");
    state.className = "specimen-state";
    const job = this.jobOf(id);
    state.textContent = describeBuild(job, summary);
    item.append(picture, name, details, state);
    if (job && isUnderWay(job)) {
      const bar = document.createElement("div");
      bar.className = "specimen-progress";
      bar.style.setProperty("--fraction", `${(100 * job.progress.fraction).toFixed(1)}%`);
      item.append(bar);
    }
    item.addEventListener("click", () => this.onPick(id));
    return item;
  }
}

export function isUnderWay(job) {
  return job.state === "queued" || job.state === "running";
}

function describeBuild(job, summary) {
  if (job?.state === "queued") return "build queued";
  if (job?.state === "running") return `building: ${Math.round(100 * job.progress.fraction)} %` + (job.progress.message ? `, ${job.progress.message}` : "");
  if (job?.state === "failed") return `build failed: ${job.error?.error ?? "no reason given"}` + (summary ? " (the previous build is shown)" : "");
  return summary ? "built" : "";
}
