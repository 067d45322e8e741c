// PolyDDA home page: upload a scene to start a process (POST /jobs, with the API key the
// page keeps in its cookie sent as X-API-Key), and follow the jobs that have not ended.
const cfg = JSON.parse(document.getElementById("home-config").textContent);
const $ = (id) => document.getElementById(id);

function key() {
  const m = document.cookie.match(/(?:^|; )polydda_key=([^;]*)/);
  return m ? decodeURIComponent(m[1]) : null;
}

function say(text, problems) {
  $("upload-status").textContent = text;
  $("upload-problems").replaceChildren(...(problems || []).map((p) => {
    const li = document.createElement("li");
    li.textContent = p;
    return li;
  }));
}

$("upload-form").addEventListener("submit", async (e) => {
  e.preventDefault();
  const file = $("scene-file").files[0];
  if (!file) { say("choose a scene file"); return; }
  const text = await file.text();
  try { JSON.parse(text); } catch (err) { say(`${file.name} is not JSON: ${err.message}`); return; }
  const headers = { "Content-Type": "application/json", Accept: "application/json" };
  if (key()) headers["X-API-Key"] = key();
  const process = $("process").value;
  say(`submitting ${file.name}…`);
  $("upload").disabled = true;
  try {
    const url = `${cfg.root}/jobs` + (process ? `?process=${encodeURIComponent(process)}` : "");
    const r = await fetch(url, { method: "POST", headers, body: text, credentials: "same-origin" });
    const doc = await r.json().catch(() => ({}));
    if (r.status === 201) {
      say(`started job ${doc.jobID}`);
      window.polyddaSubmitted = doc.jobID;
      $("upload-form").reset();
      setTimeout(() => location.reload(), 300);
    } else {
      // a problem document: its fields named, one per line
      say(`${r.status} ${doc.title || r.statusText}` + (doc.errors ? "" : `: ${doc.detail || ""}`),
          (doc.errors || []).map((p) => (p.loc ? `${p.loc}: ${p.msg}` : p.msg)));
    }
  } catch (err) {
    say(`could not submit: ${err.message}`);
  } finally {
    $("upload").disabled = false;
  }
});

// rows of jobs that have not ended follow their status; when one ends the page reloads (for
// its report link), unless a file is being chosen
const active = [...document.querySelectorAll("#jobs tr[data-active]")];
if (active.length) {
  setInterval(async () => {
    for (const row of active) {
      const r = await fetch(`${cfg.root}/jobs/${row.dataset.job}`,
                            { credentials: "same-origin", headers: key() ? { "X-API-Key": key() } : {} });
      if (!r.ok) continue;
      const doc = await r.json();
      row.querySelector(".status").textContent = doc.status;
      row.querySelector(".progress").textContent = `${Math.floor(doc.progress || 0)} %`;
      if (!["accepted", "running"].includes(doc.status) && !$("scene-file").value) location.reload();
    }
  }, cfg.poll_ms);
}
