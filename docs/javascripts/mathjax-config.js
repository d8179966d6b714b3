// MathJax 3 for pymdownx.arithmatex (generic mode): typeset \( \) and \[ \] inside the .arithmatex spans only.
// tex-svg.js is copied into the built site by tools/mkdocs_hooks.py when `make docs` has installed it.
window.MathJax = {
  tex: {inlineMath: [["\\(", "\\)"]], displayMath: [["\\[", "\\]"]], processEscapes: true, processEnvironments: true},
  options: {ignoreHtmlClass: ".*|", processHtmlClass: "arithmatex"},
};
document$.subscribe(() => {
  if (window.MathJax.typesetPromise) {
    window.MathJax.typesetPromise();
  }
});
