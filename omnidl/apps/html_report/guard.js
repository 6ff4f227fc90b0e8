// Runs first: every script error, failed resource and console.error of the page is listed in a red banner at
// the top (and in document.body.dataset.problems), so a broken report says so instead of looking empty.
(function () {
  "use strict";
  // the one note three.js 0.159's classic build prints on load (see vendor/README.md); nothing else is hidden
  var IGNORED_NOTES = [/^Scripts "build\/three\.js" and "build\/three\.min\.js" are deprecated/];
  var problems = [];
  function show() {
    var box = document.getElementById("problems");
    if (document.body) document.body.dataset.problems = String(problems.length);
    if (box) { box.hidden = false; box.textContent = "This page hit a problem:\n" + problems.join("\n"); }
  }
  function report(text) { problems.push(text); if (document.readyState !== "loading") show(); }
  window.omnidlProblems = problems;
  window.addEventListener("error", function (e) {
    if (e.target && e.target !== window && (e.target.src || e.target.href)) {
      report("could not load " + (e.target.src || e.target.href));
    } else {
      report((e.message || "error") + (e.filename ? " (" + e.filename + ":" + e.lineno + ")" : ""));
    }
  }, true);
  window.addEventListener("unhandledrejection", function (e) { report("unhandled: " + e.reason); });
  var origError = console.error, origWarn = console.warn;
  console.error = function () {
    report(Array.prototype.join.call(arguments, " "));
    origError.apply(console, arguments);
  };
  console.warn = function () {
    var text = Array.prototype.join.call(arguments, " ");
    if (IGNORED_NOTES.some(function (r) { return r.test(text); })) return;
    origWarn.apply(console, arguments);
  };
  document.addEventListener("DOMContentLoaded", function () {
    document.body.dataset.problems = String(problems.length);
    if (problems.length) show();
  });
})();
