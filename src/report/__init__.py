"""Reports from logged MLflow runs: comparison and cost tables (Markdown, LaTeX, CSV), learning curves,
image grids and one self-contained HTML page. Entry point: `src.report.build.build_report(cfg)`."""
