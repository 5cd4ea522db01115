// FilePond's frames only while a drop area is shown (in the page's head, before FilePond).
//
// FilePond (the Files tab's drop areas, Panel's FileDropper) paints from a
// requestAnimationFrame loop that it starts as soon as its script loads and never stops:
// a frame 60 times a second for as long as the page is open, drop area or not (8.5 % of
// a core per idle page on the test machine; upstream pqina/filepond#243). FilePond starts
// no loop of its own when the page already has a "frame painter"
// (window.__framePainter, to which it adds its reader and writer). This one runs them
// every frame while a drop area is displayed, ten times a second while one exists but is
// hidden (an upload in progress still moves on), and not at all before the first one is
// created or after the last one is destroyed. It learns of drop areas by wrapping
// FilePond.create.
(function () {
  "use strict";
  if (window.__framePainter) return;
  var painter = window.__framePainter = {readers: [], writers: []};
  var ponds = [];
  var scheduled = false;

  function shown() {
    for (var i = 0; i < ponds.length; i++) {
      var el = ponds[i].element;
      if (el && el.isConnected && el.offsetWidth > 0) return true;
    }
    return false;
  }

  function frame(ts) {
    scheduled = false;
    painter.readers.forEach(function (read) { read(); });
    painter.writers.forEach(function (write) { write(ts); });
    schedule();
  }

  function schedule() {
    if (scheduled || ponds.length === 0) return;
    scheduled = true;
    if (!document.hidden && shown()) window.requestAnimationFrame(frame);
    else window.setTimeout(function () { frame(performance.now()); }, 100);
  }

  function track(pond) {
    if (!pond || typeof pond !== "object") return;
    ponds.push(pond);
    if (typeof pond.on === "function")
      pond.on("destroy", function () { ponds = ponds.filter(function (p) { return p !== pond; }); });
    schedule();
  }

  // FilePond's UMD build sets window.FilePond = {} and then fills in create().
  var filepond;
  Object.defineProperty(window, "FilePond", {
    configurable: true,
    enumerable: true,
    get: function () { return filepond; },
    set: function (value) {
      filepond = value;
      if (!value || typeof value !== "object") return;
      var create = value.create;
      var wrapped = function () {
        var pond = create.apply(this, arguments);
        track(pond);
        return pond;
      };
      Object.defineProperty(value, "create", {
        configurable: true,
        enumerable: true,
        get: function () { return typeof create === "function" ? wrapped : create; },
        set: function (f) { create = f; }
      });
    }
  });
  window.mdcoreFramePainter = painter;  // for the browser test that counts frames
})();
