
(function () {
  var errors = [];
  function show() {
    var el = document.getElementById('js-errors');
    if (!el || !document.body) { return; }
    el.textContent = errors.join('\n');
    el.hidden = errors.length === 0;
    document.body.dataset.jsErrors = String(errors.length);
  }
  function record(msg) { errors.push(String(msg)); show(); }
  window.addEventListener('error', function (e) {
    record('error: ' + (e.message || e) + ' (' + (e.filename || '') + ':' + (e.lineno || 0) + ')');
  });
  window.addEventListener('unhandledrejection', function (e) {
    var r = e.reason;
    record('unhandled rejection: ' + ((r && (r.stack || r.message)) || r));
  });
  document.addEventListener('DOMContentLoaded', show);
  // where the verdict matrix ends on the page (px from the top): "above the fold" is checkable
  window.addEventListener('load', function () {
    var m = document.getElementById('verdict-matrix');
    if (m) { document.body.dataset.verdictBottom = String(Math.round(m.getBoundingClientRect().bottom + window.scrollY)); }
  });
  window.__reportRendered = 0;
  window.__reportDone = function (id) {
    var el = document.getElementById(id);
    if (el) { el.dataset.rendered = '1'; }
    window.__reportRendered += 1;
    document.body.dataset.rendered = String(window.__reportRendered);
  };
})();
