//! The ANSUR II anthropometric survey (US Army, 2012; public domain).
//!
//! blapose samples realistic, correlated bone lengths from this population
//! instead of SMPL (whose licence forbids our use). The two public CSVs
//! (`ANSUR_II_MALE_Public.csv`, `ANSUR_II_FEMALE_Public.csv`) are latin-1,
//! and their id column is spelt differently (`subjectid` / `SubjectId`).
//!
//! A record keeps the *measurement* columns: every column between the id and
//! `Gender`. They are integers in millimetres, except `weightkg` which is in
//! tenths of a kilogram (the survey's unit). Demographic columns after
//! `Gender` (date, installation, race, age, ...) are not kept; `Gender`
//! becomes [`Sex`].

use std::path::{Path, PathBuf};

/// Male table, relative to the data root.
pub const MALE_FILE: &str = "ansur2/ANSUR_II_MALE_Public.csv";
/// Female table, relative to the data root.
pub const FEMALE_FILE: &str = "ansur2/ANSUR_II_FEMALE_Public.csv";

/// Why an ANSUR II CSV could not be read.
#[derive(Debug, thiserror::Error)]
pub enum AnsurError {
    /// The file could not be read.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        #[source]
        source: std::io::Error,
    },
    /// The CSV itself is malformed (e.g. a row with the wrong field count).
    #[error("{source_name}: malformed CSV: {source}")]
    Csv {
        /// File name or other label.
        source_name: String,
        /// The CSV error (names the line).
        #[source]
        source: csv::Error,
    },
    /// A required column is missing from the header.
    #[error("{source_name}: no {column:?} column in the header")]
    MissingColumn {
        /// File name or other label.
        source_name: String,
        /// The column.
        column: &'static str,
    },
    /// A cell that must be a number is not.
    #[error("{source_name}: line {line}, column {column:?}: {value:?} is not a number")]
    BadNumber {
        /// File name or other label.
        source_name: String,
        /// 1-based line number in the file.
        line: u64,
        /// Column name.
        column: String,
        /// The cell.
        value: String,
    },
    /// `Gender` is neither `Male` nor `Female`.
    #[error("{source_name}: line {line}: unknown Gender {value:?}")]
    BadSex {
        /// File name or other label.
        source_name: String,
        /// 1-based line number.
        line: u64,
        /// The cell.
        value: String,
    },
    /// The two files have different measurement columns.
    #[error("the male and female tables have different measurement columns")]
    ColumnMismatch,
}

/// Sex as recorded in the survey's `Gender` column (`Male`, `Female`).
pub use blapose_core::Sex;

/// One person.
#[derive(Debug, Clone, PartialEq)]
pub struct AnsurRecord {
    /// The survey's subject id.
    pub subject_id: u64,
    /// Sex.
    pub sex: Sex,
    /// Measurements, indexed like [`AnsurTable::columns`] (mm; `weightkg`
    /// in 0.1 kg).
    pub values: Vec<f32>,
}

/// A table of people with named measurement columns.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct AnsurTable {
    /// Measurement column names (lower case, as in the CSV header).
    pub columns: Vec<String>,
    /// The people.
    pub records: Vec<AnsurRecord>,
}

impl AnsurTable {
    /// Index of a measurement column.
    pub fn column_index(&self, name: &str) -> Option<usize> {
        self.columns.iter().position(|c| c == name)
    }

    /// One person's measurement by column name.
    pub fn value(&self, record: &AnsurRecord, column: &str) -> Option<f32> {
        record.values.get(self.column_index(column)?).copied()
    }

    /// A whole column.
    pub fn column(&self, name: &str) -> Option<Vec<f32>> {
        let i = self.column_index(name)?;
        Some(self.records.iter().map(|r| r.values[i]).collect())
    }
}

/// Decode latin-1 bytes (every byte is the code point of the same value).
fn latin1(bytes: &[u8]) -> String {
    bytes.iter().map(|&b| b as char).collect()
}

/// Parse one ANSUR II CSV (latin-1 bytes). `source_name` labels errors.
pub fn parse_ansur_csv(bytes: &[u8], source_name: &str) -> Result<AnsurTable, AnsurError> {
    let text = latin1(bytes);
    let csv_err = |source| AnsurError::Csv {
        source_name: source_name.to_owned(),
        source,
    };
    let mut reader = csv::ReaderBuilder::new()
        .has_headers(true)
        .from_reader(text.as_bytes());
    let header = reader.headers().map_err(csv_err)?.clone();
    let missing = |column| AnsurError::MissingColumn {
        source_name: source_name.to_owned(),
        column,
    };
    let id_col = header
        .iter()
        .position(|h| h.eq_ignore_ascii_case("subjectid"))
        .ok_or_else(|| missing("subjectid"))?;
    let sex_col = header
        .iter()
        .position(|h| h == "Gender")
        .ok_or_else(|| missing("Gender"))?;
    if sex_col <= id_col {
        return Err(missing("measurements between subjectid and Gender"));
    }
    let columns: Vec<String> = header
        .iter()
        .skip(id_col + 1)
        .take(sex_col - id_col - 1)
        .map(str::to_owned)
        .collect();
    let mut records = Vec::new();
    for row in reader.records() {
        let row = row.map_err(csv_err)?;
        let line = row.position().map_or(0, |p| p.line());
        let number = |i: usize| -> Result<f32, AnsurError> {
            let cell = row.get(i).unwrap_or("");
            cell.trim()
                .parse::<f32>()
                .ok()
                .filter(|v| v.is_finite())
                .ok_or_else(|| AnsurError::BadNumber {
                    source_name: source_name.to_owned(),
                    line,
                    column: header.get(i).unwrap_or("?").to_owned(),
                    value: cell.to_owned(),
                })
        };
        let id_cell = row.get(id_col).unwrap_or("");
        let subject_id = id_cell
            .trim()
            .parse::<u64>()
            .map_err(|_| AnsurError::BadNumber {
                source_name: source_name.to_owned(),
                line,
                column: header.get(id_col).unwrap_or("subjectid").to_owned(),
                value: id_cell.to_owned(),
            })?;
        let sex = match row.get(sex_col).map(str::trim) {
            Some("Male") => Sex::Male,
            Some("Female") => Sex::Female,
            other => {
                return Err(AnsurError::BadSex {
                    source_name: source_name.to_owned(),
                    line,
                    value: other.unwrap_or("").to_owned(),
                })
            }
        };
        let values = (id_col + 1..sex_col)
            .map(number)
            .collect::<Result<Vec<_>, _>>()?;
        records.push(AnsurRecord {
            subject_id,
            sex,
            values,
        });
    }
    Ok(AnsurTable { columns, records })
}

/// Read one ANSUR II CSV file.
pub fn read_ansur_csv(path: &Path) -> Result<AnsurTable, AnsurError> {
    let bytes = std::fs::read(path).map_err(|source| AnsurError::Io {
        path: path.to_owned(),
        source,
    })?;
    parse_ansur_csv(&bytes, &path.display().to_string())
}

/// Both tables under the data root, merged (male rows first).
pub fn load_ansur(root: &Path) -> Result<AnsurTable, AnsurError> {
    let mut male = read_ansur_csv(&root.join(MALE_FILE))?;
    let female = read_ansur_csv(&root.join(FEMALE_FILE))?;
    if male.columns != female.columns {
        return Err(AnsurError::ColumnMismatch);
    }
    male.records.extend(female.records);
    Ok(male)
}

#[cfg(test)]
mod tests {
    use super::*;

    const SMALL: &[u8] = b"SubjectId,stature,weightkg,Gender,SubjectsBirthLocation\n\
        1,1776,815,Male,M\xe9xico\n\
        2,1560,657,Female,Iowa\n";

    #[test]
    fn parses_latin1_and_either_id_spelling() {
        let t = parse_ansur_csv(SMALL, "small").unwrap();
        assert_eq!(t.columns, ["stature", "weightkg"]);
        assert_eq!(t.records.len(), 2);
        assert_eq!(t.records[0].sex, Sex::Male);
        assert_eq!(t.value(&t.records[1], "stature"), Some(1560.0));
        assert_eq!(t.column("weightkg"), Some(vec![815.0, 657.0]));
        let lower = std::str::from_utf8(&SMALL[..9]).unwrap().to_lowercase();
        let mut other = lower.into_bytes();
        other.extend_from_slice(&SMALL[9..]);
        assert_eq!(parse_ansur_csv(&other, "lower").unwrap().records.len(), 2);
    }

    #[test]
    fn malformed_csv_is_a_typed_error() {
        let e = parse_ansur_csv(b"SubjectId,stature,Gender\n1,17x6,Male\n", "f.csv").unwrap_err();
        assert!(
            matches!(&e, AnsurError::BadNumber { line: 2, column, value, .. } if column == "stature" && value == "17x6"),
            "{e}"
        );
        let e = parse_ansur_csv(b"SubjectId,stature,Gender\n1,1776\n", "f.csv").unwrap_err();
        assert!(matches!(e, AnsurError::Csv { .. }), "{e}");
        let e = parse_ansur_csv(b"id,stature,Gender\n1,1776,Male\n", "f.csv").unwrap_err();
        assert!(
            matches!(
                e,
                AnsurError::MissingColumn {
                    column: "subjectid",
                    ..
                }
            ),
            "{e}"
        );
        let e = parse_ansur_csv(b"SubjectId,stature\n1,1776\n", "f.csv").unwrap_err();
        assert!(
            matches!(
                e,
                AnsurError::MissingColumn {
                    column: "Gender",
                    ..
                }
            ),
            "{e}"
        );
        let e = parse_ansur_csv(b"SubjectId,stature,Gender\n1,1776,X\n", "f.csv").unwrap_err();
        assert!(matches!(e, AnsurError::BadSex { .. }), "{e}");
        let e = parse_ansur_csv(b"SubjectId,stature,Gender\n1,NaN,Male\n", "f.csv").unwrap_err();
        assert!(matches!(e, AnsurError::BadNumber { .. }), "{e}");
        assert!(matches!(
            read_ansur_csv(Path::new("/nonexistent.csv")),
            Err(AnsurError::Io { .. })
        ));
    }
}
