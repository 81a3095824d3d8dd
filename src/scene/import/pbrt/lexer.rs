//! The pbrt tokenizer: quoted strings, brackets, numbers and bare words, each with its file and
//! line.

use crate::scene::SceneError;
use std::path::Path;

/// Where a token stands: the index of its file in the parser's file list, and the line.
#[derive(Clone, Copy, Debug)]
pub(super) struct Loc {
    pub(super) file: u16,
    pub(super) line: u32,
}

/// A token's kind and value.
#[derive(Clone, Debug, PartialEq)]
pub(super) enum Tok {
    /// A bare word: a directive name, or `true`/`false`.
    Word(String),
    Str(String),
    Num(f64),
    Open,
    Close,
}

/// A token and its place.
#[derive(Clone, Debug)]
pub(super) struct Token {
    pub(super) tok: Tok,
    pub(super) loc: Loc,
}

/// A token for messages: `'Shape'`, `"sphere"`, `the number 2`.
pub(super) fn describe(t: &Tok) -> String {
    match t {
        Tok::Word(w) => format!("'{w}'"),
        Tok::Str(s) => format!("\"{s}\""),
        Tok::Num(n) => format!("the number {n}"),
        Tok::Open => "'['".into(),
        Tok::Close => "']'".into(),
    }
}

/// Splits pbrt text into tokens: quoted strings (with C escapes), `[`, `]`, numbers and bare
/// words; `#` starts a comment that runs to the end of the line.
pub(super) fn tokenize(text: &str, file: u16, path: &Path) -> Result<Vec<Token>, SceneError> {
    let err = |line: u32, m: String| SceneError::new(path, format!("line {line}"), m);
    let mut out = Vec::new();
    let mut line = 1u32;
    let mut it = text.chars().peekable();
    while let Some(c) = it.next() {
        let loc = Loc { file, line };
        match c {
            '\n' => line += 1,
            c if c.is_whitespace() => {}
            '#' => {
                while it.peek().is_some_and(|&n| n != '\n') {
                    it.next();
                }
            }
            '[' => out.push(Token {
                tok: Tok::Open,
                loc,
            }),
            ']' => out.push(Token {
                tok: Tok::Close,
                loc,
            }),
            '"' => {
                let mut s = String::new();
                loop {
                    match it.next() {
                        None => return Err(err(loc.line, "unterminated string".into())),
                        Some('"') => break,
                        Some('\n') => {
                            return Err(err(loc.line, "string is not closed on its line".into()));
                        }
                        Some('\\') => {
                            let e = match it.next() {
                                Some('n') => '\n',
                                Some('t') => '\t',
                                Some('r') => '\r',
                                Some('b') => '\u{8}',
                                Some('f') => '\u{c}',
                                Some(ch @ ('\\' | '\'' | '"')) => ch,
                                other => {
                                    return Err(err(
                                        loc.line,
                                        format!(
                                            "unknown escape sequence '\\{}'",
                                            other.unwrap_or(' ')
                                        ),
                                    ));
                                }
                            };
                            s.push(e);
                        }
                        Some(ch) => s.push(ch),
                    }
                }
                out.push(Token {
                    tok: Tok::Str(s),
                    loc,
                });
            }
            _ => {
                let mut w = String::from(c);
                while let Some(&n) = it.peek() {
                    if n.is_whitespace() || matches!(n, '[' | ']' | '"' | '#') {
                        break;
                    }
                    w.push(n);
                    it.next();
                }
                let tok = if c.is_ascii_digit() || matches!(c, '-' | '+' | '.') {
                    match w.parse::<f64>() {
                        Ok(v) if v.is_finite() => Tok::Num(v),
                        _ => return Err(err(loc.line, format!("malformed number '{w}'"))),
                    }
                } else if c.is_ascii_alphabetic()
                    && w.chars().all(|ch| ch.is_ascii_alphanumeric() || ch == '_')
                {
                    Tok::Word(w)
                } else {
                    return Err(err(loc.line, format!("unexpected text '{w}'")));
                };
                out.push(Token { tok, loc });
            }
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tokens_carry_lines_and_kinds() {
        let t = tokenize(
            "Shape \"sphere\" # c\n  \"float radius\" [ 2.5 ]\n-1e-3",
            0,
            Path::new("x.pbrt"),
        )
        .unwrap();
        let kinds: Vec<&Tok> = t.iter().map(|t| &t.tok).collect();
        assert_eq!(
            kinds,
            vec![
                &Tok::Word("Shape".into()),
                &Tok::Str("sphere".into()),
                &Tok::Str("float radius".into()),
                &Tok::Open,
                &Tok::Num(2.5),
                &Tok::Close,
                &Tok::Num(-1e-3),
            ]
        );
        assert_eq!(
            t.iter().map(|t| t.loc.line).collect::<Vec<_>>(),
            vec![1, 1, 2, 2, 2, 2, 3]
        );
        let e = tokenize("Shape\n\n 1.2.3", 0, Path::new("x.pbrt")).unwrap_err();
        assert_eq!(e.location, "line 3");
        assert!(tokenize("\"open", 0, Path::new("x.pbrt")).is_err());
    }
}
