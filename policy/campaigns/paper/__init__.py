"""The paper's four scenarios and its Table I comparison, for every controller
(`tools/paper.py`, docs/results.md): the settings and the docs block's markers (`settings`),
the table's runs (`table`), the figures (`figures`), the block's text (`markdown`) and what
the command does with its options (`command`)."""
