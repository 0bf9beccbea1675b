"""Summarises PC samples (hexadecimal, one a line on stdin) of a firmware image: the share of
samples by the innermost frame in the core's own source (library frames such as iterator
adapters are folded into their caller) and by the outermost core frame below the localizer
(the pipeline stage). Usage: python3 profile_report.py IMAGE [TOP]."""

import collections
import subprocess
import sys

LIBRARY = ("/rustc/", "/library/", "/.cargo/registry/")


def frames(image, addresses):
    """Inlined frame chains (innermost first) of each address, as (function, file:line)."""
    text = subprocess.run(
        ["llvm-symbolizer", "--obj=" + image, "--inlining", "--functions=short", "--demangle"],
        input="\n".join(addresses) + "\n", capture_output=True, text=True, check=True).stdout
    chains = []
    for block in text.strip("\n").split("\n\n"):
        lines = block.split("\n")
        chains.append([(lines[i], lines[i + 1]) for i in range(0, len(lines) - 1, 2)])
    return chains


def own(chain):
    """The frames of the repository's code (not the standard library or other crates)."""
    return [f for f in chain if not any(p in f[1] for p in LIBRARY)] or chain[:1]


def short(frame):
    function, place = frame
    name = function.split("<")[0]
    path = place.split("/core/src/")[-1].split("/firmware/src/")[-1]
    return name, path


def main():
    image, top = sys.argv[1], int(sys.argv[2]) if len(sys.argv) > 2 else 25
    samples = [line.strip() for line in sys.stdin if line.strip()]
    counts = collections.Counter(samples)
    addresses = sorted(counts)
    by_function, by_line, by_stage = collections.Counter(), collections.Counter(), collections.Counter()
    for address, chain in zip(addresses, frames(image, ["0x" + a for a in addresses])):
        n = counts[address]
        mine = own(chain)
        name, place = short(mine[0])
        by_function[name] += n
        by_line[f"{name} {place.rsplit(':', 1)[0]}"] += n
        by_stage[" > ".join(short(f)[0] for f in reversed(mine[-4:]))] += n
    total = len(samples)
    for title, table in (("function", by_function), ("line", by_line), ("call chain (outermost 4)", by_stage)):
        print(f"== by {title} ({total} samples)")
        for key, n in table.most_common(top):
            print(f"{100 * n / total:6.2f} %  {key}")


if __name__ == "__main__":
    main()
