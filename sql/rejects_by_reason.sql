-- Rejects by reason: which input rows were not used, from which table and stage, and why.
-- Columns: input_table, stage, reason, rows, example_row_index.
SELECT input_table,
       stage,
       reason,
       count(*)       AS rows,
       min(row_index) AS example_row_index
FROM rejects
GROUP BY input_table, stage, reason
ORDER BY rows DESC, input_table, reason;
