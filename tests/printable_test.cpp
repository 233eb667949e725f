// Names and log lines from elsewhere, made safe for a terminal and for file names (common/printable.h).
#include "common/printable.h"

#include <gtest/gtest.h>

namespace gaps {
namespace {

TEST(Printable, ControlCharactersBecomeEscapesAndTheRestStays) {
  EXPECT_EQ(printable("fern-3 views"), "fern-3 views");
  EXPECT_EQ(printable("job\x1b[2J\x1b[31mred"), "job\\x1b[2J\\x1b[31mred");
  EXPECT_EQ(printable("a\nb\tc\x7f"), "a\\x0ab\\x09c\\x7f");
  EXPECT_EQ(printable("a\nb\tc\x07", /*keep_lines=*/true), "a\nb\tc\\x07");
  EXPECT_EQ(printable("caf\xc3\xa9"), "caf\xc3\xa9");  // UTF-8 is not a control character
  EXPECT_EQ(printable(std::string("nul\0end", 7)), "nul\\x00end");
}

TEST(Printable, FileNamesLoseTheirControlCharactersButNotTheirLength) {
  EXPECT_EQ(safe_file_name("renders/img\x1b]0;x\x07.png"), "renders/img_]0;x_.png");
  EXPECT_EQ(safe_file_name("plain.png"), "plain.png");
  EXPECT_TRUE(has_control_characters("a\rb"));
  EXPECT_FALSE(has_control_characters("a b"));
}

}  // namespace
}  // namespace gaps
