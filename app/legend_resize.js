// One layout and paint of a plot with a legend, not two (loaded by app/main.py).
//
// BokehJS 3.9 draws a legend as HTML and watches its element with a ResizeObserver
// whose callback asks the whole plot for a new layout. A ResizeObserver always reports
// an element once when it starts watching it, so every plot with a legend was laid out
// and painted a second time, at the same size, one frame after it was first drawn
// (40-60 ms of the browser's main thread for the Data tab's two plots): on the first
// page and whenever a tab or a rebuilt figure is shown. Here the callback asks for a
// layout only when the legend's size differs from the one the plot's last layout
// measured (LegendView's bbox), which is the case whenever the legend really changed
// size.
//
// If BokehJS changes so that the legend view is not where this expects it, nothing is
// patched and Bokeh behaves as it always did (one redundant paint).
(function () {
  "use strict";
  var Bokeh = window.Bokeh;
  if (!Bokeh || typeof Bokeh.require !== "function") return;
  var legend;
  try {
    legend = Bokeh.require("models/annotations/legend");
  } catch (e) {
    return;
  }
  var proto = legend && legend.LegendView && legend.LegendView.prototype;
  if (!proto || typeof proto.initialize !== "function") return;
  var initialize = proto.initialize;
  proto.initialize = function () {
    initialize.apply(this, arguments);
    var view = this;
    var observer = this._resize_observer;
    if (!observer || typeof ResizeObserver !== "function") return;
    observer.disconnect();
    this._resize_observer = new ResizeObserver(function (entries) {
      var entry = entries[entries.length - 1];
      var box = entry.borderBoxSize && entry.borderBoxSize[0];
      var width = box ? box.inlineSize : entry.contentRect.width;
      var height = box ? box.blockSize : entry.contentRect.height;
      var laid = view._bbox;
      if (laid && Math.abs(laid.width - width) < 0.5 && Math.abs(laid.height - height) < 0.5)
        return;                        // the size the plot was laid out with: nothing to do
      view.request_layout();
    });
    this._resize_observer.observe(this.el, {box: "border-box"});
  };
  window.mdcoreLegendResize = true;    // for the browser test that counts paints
})();
