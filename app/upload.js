// The Files tab's drop areas (app/upload.py): a file goes to the server in chunks, each sent
// after the server counted the one before (so it can refuse a file before the rest is sent);
// its verdict is shown under the area. Every text is set with textContent, never as markup.

function base64(buffer) {
  const bytes = new Uint8Array(buffer)
  let text = ""
  for (let i = 0; i < bytes.length; i += 0x8000)
    text += String.fromCharCode.apply(null, bytes.subarray(i, i + 0x8000))
  return btoa(text)
}

export function render({model, el}) {
  const area = document.createElement("label")
  area.className = "mdcore-drop"
  const input = document.createElement("input")
  input.type = "file"
  input.accept = model.accept
  const prompt = document.createElement("span")
  prompt.className = "mdcore-drop-prompt"
  prompt.textContent = model.prompt
  const status = document.createElement("div")
  status.className = "mdcore-drop-status"
  status.setAttribute("role", "status")
  const bar = document.createElement("progress")
  bar.max = 1
  bar.value = 0
  area.append(input, prompt, bar)
  el.append(area, status)

  let pending = null        // resolves with the server's answer to the last message
  let sending = false

  function show() {
    status.textContent = model.message
    status.dataset.state = model.state
    area.dataset.state = model.state
    bar.style.visibility = model.state === "receiving" ? "visible" : "hidden"
  }
  show()
  model.on(["state", "message"], show)
  model.on("ack", () => {
    const answer = pending
    pending = null
    if (answer) answer(model.state === "receiving")
  })

  function ask(message) {
    return new Promise(resolve => {
      pending = resolve
      model.send_msg(message)
    })
  }

  async function upload(file) {
    if (sending) return
    sending = true
    bar.value = 0
    // At once, before the server answers: the line under the area is never the verdict
    // on the file sent before.
    status.textContent = `${file.name}: sending …`
    status.dataset.state = area.dataset.state = "sending"
    try {
      if (!await ask({start: file.name, size: file.size})) return
      for (let offset = 0; offset < file.size; offset += model.chunk_bytes) {
        const chunk = await file.slice(offset, offset + model.chunk_bytes).arrayBuffer()
        if (!await ask({offset, data: base64(chunk)})) return
        bar.value = Math.min(1, (offset + chunk.byteLength) / Math.max(file.size, 1))
      }
      await ask({end: file.name})
    } finally {
      sending = false
      input.value = ""        // the same file chosen again is a new upload
      show()
    }
  }

  input.addEventListener("change", () => {
    if (input.files.length) upload(input.files[0])
  })
  for (const name of ["dragenter", "dragover"]) {
    area.addEventListener(name, event => {
      event.preventDefault()
      area.classList.add("mdcore-drop-over")
    })
  }
  area.addEventListener("dragleave", () => area.classList.remove("mdcore-drop-over"))
  area.addEventListener("drop", event => {
    event.preventDefault()
    area.classList.remove("mdcore-drop-over")
    const files = event.dataTransfer ? event.dataTransfer.files : []
    if (files.length) upload(files[0])
  })
}
