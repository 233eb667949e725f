#include "server/sql_driver.h"

namespace gaps {

int64_t sql_int(const std::optional<std::string>& value) { return value ? std::stoll(*value) : 0; }
double sql_real(const std::optional<std::string>& value) { return value ? std::stod(*value) : 0.0; }

}  // namespace gaps
