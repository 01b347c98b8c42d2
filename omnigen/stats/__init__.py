"""The dataset statistics report (`omnigen stats`, docs/stats.md).

compute.py turns a dataset's columns into the numbers (stats.json); health.py flags what looks
wrong; plots.py draws figures from the numbers alone; gallery.py draws sample frames with
omnigen.draw; report.py runs them in turn and renders templates/index.html.j2. Importing this
package imports none of them, so matplotlib loads only when a report is made.
"""
