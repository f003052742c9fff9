// MathJax 3 configuration, read before docs/assets/mathjax/tex-svg.js (copied into the
// site by docs/hooks.py) loads. Arithmatex (generic mode) writes \( \) and \[ \] into
// pages and docstrings; notebook cells use $ $. Code is skipped (MathJax's default
// skipHtmlTags). SVG output needs no web fonts.
window.MathJax = {
  tex: {
    inlineMath: [["\\(", "\\)"], ["$", "$"]],
    displayMath: [["\\[", "\\]"], ["$$", "$$"]],
    processEscapes: true,
    processEnvironments: true,
  },
};
// Material's instant navigation (if enabled) swaps pages without reloading: typeset each.
if (typeof document$ !== "undefined") {
  document$.subscribe(() => {
    if (window.MathJax && MathJax.typesetPromise) {
      MathJax.typesetClear();
      MathJax.texReset();
      MathJax.typesetPromise();
    }
  });
}
