# Study report: one self-contained HTML page per subject (atlases, quality, 3-D views, changes),
# and its printed form, report.pdf (the summary page and a page per change card).

# Keys of the PDF only: changing them does not re-run the HTML report.
PDF_KEYS = ("pdf", "chromium")


rule report:
    input:
        unpack(report_inputs),
    output:
        html=report(
            "results/{subject}/report.html",
            caption="../report/study_report.rst",
            category="Study report",
            labels={"subject": "{subject}", "format": "HTML"},
        ),
    params:
        report={k: v for k, v in config["report"].items() if k not in PDF_KEYS},
        sessions=lambda wc: report_sessions(wc.subject),
        pairs=lambda wc: [list(p) for p in comparison_pairs(wc.subject)],
    log:
        "logs/{subject}/report.log",
    benchmark:
        "benchmarks/{subject}/report.tsv"
    threads: 1
    resources:
        mem_mb=3000,
        runtime=10,
    conda:
        CONDA_ENV
    script:
        "../../scripts/report.py"


# Needs headless Chromium (`make browser`), so it is a target of its own: among the default
# targets only with report.pdf: true; else `snakemake results/{subject}/report.pdf`.
rule report_pdf:
    input:
        html="results/{subject}/report.html",
    output:
        pdf=report(
            "results/{subject}/report.pdf",
            caption="../report/study_report_pdf.rst",
            category="Study report",
            labels={"subject": "{subject}", "format": "PDF"},
        ),
    params:
        chromium=config["report"]["chromium"],
    log:
        "logs/{subject}/report_pdf.log",
    benchmark:
        "benchmarks/{subject}/report_pdf.tsv"
    threads: 1
    resources:
        mem_mb=2000,
        runtime=10,
    conda:
        CONDA_ENV
    script:
        "../../scripts/report_pdf.py"
