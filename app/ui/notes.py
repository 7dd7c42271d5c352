"""What the page says the moment it changes what was typed (run by the browser on load): a
number typed outside a slider's (or a number box's) range is put back inside it, where the box
would otherwise keep showing the typed number while the slider sends the clamped one; text pasted or typed past a
box's character limit is cut, which the browser otherwise does silently. Both leave a note
under the box (class salad-note), which goes when the next value fits."""

NOTES_JS = r"""
() => {
  // capture-phase listeners on the document: they outlive Gradio re-rendering the components
  const NOTE = "salad-note";

  function showNote(block, text) {
    let note = block.querySelector("." + NOTE);
    if (!note) {
      note = document.createElement("div");
      note.className = NOTE;
      note.setAttribute("role", "status");
      block.appendChild(note);
    }
    note.textContent = text;
  }

  function clearNote(block) {
    const note = block && block.querySelector("." + NOTE);
    if (note) note.remove();
  }

  function fmt(x) {
    return String(Math.round(x * 1e6) / 1e6);
  }

  function checkNumber(box) {
    const block = box.closest(".block");
    // a slider's limits are on its range input; a number box's on the box itself
    const limits = block && (block.querySelector("input[type=range]") || box);
    if (!limits || limits.min === "" || limits.max === "") return;
    const raw = box.value.trim();
    const value = Number(raw);
    const lo = Number(limits.min), hi = Number(limits.max);
    if (raw === "" || !Number.isFinite(value) || (value >= lo && value <= hi)) {
      clearNote(block);
      return;
    }
    const clamped = Math.min(hi, Math.max(lo, value));
    box.value = fmt(clamped);
    box.dispatchEvent(new Event("input", { bubbles: true }));
    const label = (block.querySelector("[data-testid=block-info]") || {}).textContent || "the value";
    const limit = value > hi ? `the largest is ${fmt(hi)}` : `the smallest is ${fmt(lo)}`;
    showNote(block, `${raw} is out of range for ${label.trim()} (${limit}): set to ${fmt(clamped)}.`);
  }

  function checkLength(area, pasted) {
    const block = area.closest(".block");
    const limit = area.maxLength;
    if (!block || !(limit > 0)) return;
    if (pasted !== undefined) {
      const room = limit - area.value.length + (area.selectionEnd - area.selectionStart);
      if (pasted.length > room) {
        showNote(block, `The text is limited to ${limit} characters: ${pasted.length - room} pasted characters were cut.`);
        return;
      }
    }
    if (area.value.length >= limit) {
      showNote(block, `The text is limited to ${limit} characters; what is typed beyond that is not taken.`);
    } else {
      clearNote(block);
    }
  }

  const isNumber = (el) => el instanceof HTMLInputElement && el.type === "number";
  const isText = (el) => (el instanceof HTMLTextAreaElement || (el instanceof HTMLInputElement && el.type === "text"))
    && el.maxLength > 0;
  // Capture phase: the box is corrected before the slider reads it.
  document.addEventListener("keydown", (e) => { if (e.key === "Enter" && isNumber(e.target)) checkNumber(e.target); }, true);
  document.addEventListener("focusout", (e) => { if (isNumber(e.target)) checkNumber(e.target); }, true);
  document.addEventListener("input", (e) => {
    if (e.target instanceof HTMLInputElement && e.target.type === "range") clearNote(e.target.closest(".block"));
    else if (isText(e.target)) checkLength(e.target);
  }, true);
  document.addEventListener("paste", (e) => {
    if (isText(e.target)) checkLength(e.target, (e.clipboardData && e.clipboardData.getData("text")) || "");
  }, true);
}
"""
