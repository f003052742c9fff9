// MathJax 3 configuration, read before docs/assets/mathjax/tex-chtml.js loads.
// Arithmatex (generic mode) writes \( \) and \[ \] into pages and docstrings; notebook
// cells use $ $. Code blocks are skipped (MathJax's default skipHtmlTags).
window.MathJax = {
  tex: {
    inlineMath: [["\\(", "\\)"], ["$", "$"]],
    displayMath: [["\\[", "\\]"], ["$$", "$$"]],
    processEscapes: true,
    processEnvironments: true,
  },
  options: { ignoreHtmlClass: "tex2jax_ignore", processHtmlClass: "arithmatex|jp-RenderedMarkdown" },
};
// Material's instant navigation swaps pages without reloading: typeset each new one.
if (typeof document$ !== "undefined") {
  document$.subscribe(() => {
    if (window.MathJax && MathJax.typesetPromise) {
      MathJax.startup.output.clearCache();
      MathJax.typesetClear();
      MathJax.texReset();
      MathJax.typesetPromise();
    }
  });
}
