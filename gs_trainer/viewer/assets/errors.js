// Loaded first: every uncaught error, rejected promise and console.error of the page is shown in #gaps-errors
// and counted in <html data-errors>, where a person sees it and a headless browser's --dump-dom reads it.
'use strict';

(() => {
  const errors = [];
  const report = (message) => {
    errors.push(String(message));
    document.documentElement.dataset.errors = String(errors.length);
    const box = document.getElementById('gaps-errors');
    if (box) {
      box.hidden = false;
      box.textContent = errors.join('\n');
    }
  };
  window.addEventListener('error', (e) => report(`${e.message} (${e.filename}:${e.lineno}:${e.colno})`));
  window.addEventListener('unhandledrejection', (e) => {
    const reason = e.reason;
    report(`unhandled rejection: ${(reason && (reason.stack || reason.message)) || reason}`);
  });
  const consoleError = console.error.bind(console);
  console.error = (...args) => {
    report(args.map((a) => (a && a.stack) || String(a)).join(' '));
    consoleError(...args);
  };
  window.gapsReportError = report;
})();
