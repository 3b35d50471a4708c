// The instruction-collection page. Plain DOM, no build step. Every piece of text that comes from
// the server or the writer is set with textContent, never parsed as HTML.
"use strict";

const WRITER_KEY = "demo-factory-writer";
const SKIPPED_KEY = "demo-factory-skipped";

const page = {
  writer: null,
  current: null,   // the variation on screen: {id, index, count, pictures}
  last: null,      // the writer's last entry
  limits: { instruction_min: 3, instruction_max: 300, writer_max: 32 },
};

const $ = (id) => document.getElementById(id);

async function api(method, url, body) {
  const options = { method, headers: {} };
  if (body !== undefined) {
    options.headers["Content-Type"] = "application/json";
    options.body = JSON.stringify(body);
  }
  const response = await fetch(url, options);
  let payload = null;
  try {
    payload = await response.json();
  } catch (_) {
    payload = null;
  }
  if (!response.ok) {
    throw new Error((payload && payload.error) || `${response.status} ${response.statusText}`);
  }
  return payload;
}

function say(text, kind) {
  const message = $("message");
  message.textContent = text;
  message.className = kind || "";
}

function skipped() {
  try {
    return JSON.parse(sessionStorage.getItem(SKIPPED_KEY) || "[]");
  } catch (_) {
    return [];
  }
}

function addSkipped(id) {
  const ids = skipped();
  if (!ids.includes(id)) ids.push(id);
  sessionStorage.setItem(SKIPPED_KEY, JSON.stringify(ids));
}

// -- rendering ---------------------------------------------------------------------------------
function showProgress(state) {
  const p = state.progress;
  let text = `${p.with_instructions} of ${p.variations} scenes have at least one instruction (${p.instructions} in all).`;
  if (page.writer) text += ` You wrote ${p.mine}.`;
  $("progress-text").textContent = text;
  const list = $("histogram");
  list.replaceChildren();
  for (const bin of p.histogram) {
    const item = document.createElement("li");
    const noun = bin.instructions === 1 ? "instruction" : "instructions";
    item.textContent = `${bin.variations} with ${bin.instructions} ${noun}`;
    list.append(item);
  }
}

function showLast(last) {
  page.last = last;
  $("last").hidden = !last;
  $("edit-form").hidden = true;
  $("edit").hidden = false;
  if (!last) return;
  $("last-text").textContent = last.instruction;
  const picture = last.variation.pictures[0];
  $("last-picture").src = picture.url;
}

function showState(state) {
  page.limits = state.limits;
  $("instruction").maxLength = state.limits.instruction_max;
  $("edit-text").maxLength = state.limits.instruction_max;
  $("writer-input").maxLength = state.limits.writer_max;
  showProgress(state);
  showLast(state.last);
}

function showVariation(variation) {
  page.current = variation;
  $("done").hidden = variation !== null;
  $("work").hidden = variation === null && !page.last;
  $("entry-form").hidden = variation === null;
  const pictures = $("pictures");
  pictures.replaceChildren();
  if (variation === null) {
    $("scene-label").textContent = "";
    return;
  }
  $("scene-label").textContent =
    `Scene ${variation.index} · ${variation.count} instruction${variation.count === 1 ? "" : "s"} so far`;
  for (const picture of variation.pictures) {
    const figure = document.createElement("figure");
    const img = document.createElement("img");
    img.src = picture.url;
    img.alt = picture.caption;
    const caption = document.createElement("figcaption");
    caption.textContent = picture.caption;
    figure.append(img, caption);
    pictures.append(figure);
  }
  updateCharCount();
  $("instruction").focus();
}

function updateCharCount() {
  const length = $("instruction").value.trim().length;
  $("chars").textContent = `${length} / ${page.limits.instruction_max}`;
}

// -- actions -------------------------------------------------------------------------------------
async function refreshState() {
  const query = page.writer ? `?writer=${encodeURIComponent(page.writer)}` : "";
  showState(await api("GET", `/api/state${query}`));
}

function nextUrl(after) {
  const params = new URLSearchParams({ writer: page.writer });
  if (after !== null && after !== undefined) params.set("after", String(after));
  const ids = skipped();
  if (ids.length) params.set("skipped", ids.join(","));
  return `/api/next?${params}`;
}

async function loadNext(after) {
  const { variation } = await api("GET", nextUrl(after));
  showVariation(variation);
  if (variation) prefetchAfter(variation.id);
}

// Warm the server's picture cache and the browser's for the scene that will probably come next.
async function prefetchAfter(id) {
  try {
    const { variation } = await api("GET", nextUrl(id));
    if (variation && variation.id !== id) {
      for (const picture of variation.pictures) new Image().src = picture.url;
    }
  } catch (_) {
    // Only a speed-up; the next load reports real problems.
  }
}

async function start(writer) {
  page.writer = writer;
  localStorage.setItem(WRITER_KEY, writer);
  $("writer-name").textContent = writer;
  $("writer-line").hidden = false;
  $("writer-form-section").hidden = true;
  $("work").hidden = false;
  await refreshState();
  await loadNext(null);
}

function askForWriter() {
  page.writer = null;
  $("writer-line").hidden = true;
  $("work").hidden = true;
  $("done").hidden = true;
  $("writer-form-section").hidden = false;
  $("writer-input").value = localStorage.getItem(WRITER_KEY) || "";
  $("writer-input").focus();
}

async function onWriterSubmit(event) {
  event.preventDefault();
  const writer = $("writer-input").value.trim();
  try {
    // The server validates the id; an invalid one is answered with an error to show.
    await api("GET", `/api/state?writer=${encodeURIComponent(writer)}`);
    $("writer-message").textContent = "";
    await start(writer);
  } catch (error) {
    $("writer-message").textContent = error.message;
  }
}

async function onSubmit(event) {
  event.preventDefault();
  if (!page.current) return;
  const button = $("submit");
  button.disabled = true;
  try {
    const result = await api("POST", "/api/instructions", {
      writer: page.writer,
      variation_id: page.current.id,
      instruction: $("instruction").value,
    });
    $("instruction").value = "";
    say("Saved. Thank you!", "ok");
    showState(result.state);
    await loadNext(page.current.id);
  } catch (error) {
    say(error.message, "error");
  } finally {
    button.disabled = false;
  }
}

async function onSkip() {
  if (!page.current) return;
  addSkipped(page.current.id);
  say("");
  try {
    await loadNext(page.current.id);
  } catch (error) {
    say(error.message, "error");
  }
}

function onEdit() {
  $("edit-text").value = page.last.instruction;
  $("edit-form").hidden = false;
  $("edit").hidden = true;
  $("edit-text").focus();
}

async function onEditSubmit(event) {
  event.preventDefault();
  try {
    const result = await api("PUT", "/api/instructions/last", {
      writer: page.writer,
      instruction: $("edit-text").value,
    });
    say("Your last entry was changed.", "ok");
    showState(result.state);
  } catch (error) {
    say(error.message, "error");
  }
}

function submitOnCtrlEnter(form) {
  return (event) => {
    if (event.key === "Enter" && (event.ctrlKey || event.metaKey)) {
      event.preventDefault();
      form.requestSubmit();
    }
  };
}

document.addEventListener("DOMContentLoaded", async () => {
  $("writer-form").addEventListener("submit", onWriterSubmit);
  $("writer-change").addEventListener("click", askForWriter);
  $("entry-form").addEventListener("submit", onSubmit);
  $("skip").addEventListener("click", onSkip);
  $("edit").addEventListener("click", onEdit);
  $("edit-cancel").addEventListener("click", () => showLast(page.last));
  $("edit-form").addEventListener("submit", onEditSubmit);
  $("instruction").addEventListener("input", updateCharCount);
  $("instruction").addEventListener("keydown", submitOnCtrlEnter($("entry-form")));
  $("edit-text").addEventListener("keydown", submitOnCtrlEnter($("edit-form")));
  try {
    const saved = localStorage.getItem(WRITER_KEY);
    await refreshState();
    if (saved) {
      await start(saved);
    } else {
      askForWriter();
    }
  } catch (error) {
    askForWriter();
    $("writer-message").textContent = error.message;
  }
});
